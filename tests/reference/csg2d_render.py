"""Independent per-program 2D CSG renderer, written from the rendering rules (docs/domains.md).

It shares no code with ``plad``: it parses the program text itself, draws each
primitive with scikit-image and evaluates the postfix program with numpy.
Used by the executor tests and as the baseline of ``bench.executor``.
"""
from __future__ import annotations

import re

import numpy as np
from skimage import draw

_TOKEN = re.compile(r"([cst])\((\d+),(\d+),(\d+)\)|([+*\-$])")


def _primitive(kind: str, x: int, y: int, r: int) -> np.ndarray:
    canvas = np.zeros((64, 64), dtype=bool)
    if kind == "c":
        rr, cc = draw.disk((y, x), radius=r, shape=canvas.shape)
        canvas[rr, cc] = True
        return canvas
    if kind == "s":
        side = 1.412 * r
        r0, r1 = int(y - side / 2.0), int(y + side / 2.0)
        c0, c1 = int(x - side / 2.0), int(x + side / 2.0)
        rows, cols = [r0, r1, r1, r0], [c1, c1, c0, c0]
    else:
        side = 1.732 * r
        base = int(y + side / (2 * 1.732))
        apex = int(y - side / 1.732)
        rows, cols = [base, base, apex], [int(x - side / 2.0), int(x + side / 2.0), x]
    rr, cc = draw.polygon(rows, cols, shape=canvas.shape)
    canvas[rr, cc] = True
    rr, cc = draw.polygon_perimeter(rows, cols, shape=canvas.shape)
    canvas[rr, cc] = True
    return canvas


def render(program: str) -> np.ndarray:
    """Render one CSGNet program text (e.g. ``c(32,24,16)s(40,40,12)+$``) to bool (64, 64)."""
    stack: list[np.ndarray] = []
    for m in _TOKEN.finditer(program):
        if m.group(1):
            stack.append(_primitive(m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4))))
            continue
        op = m.group(5)
        if op == "$":
            break
        b = stack.pop()
        a = stack.pop()
        stack.append(a | b if op == "+" else a & b if op == "*" else a & ~b)
    assert len(stack) == 1, f"invalid program {program!r}"
    return stack[0]
