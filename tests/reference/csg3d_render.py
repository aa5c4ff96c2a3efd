"""Independent per-program 3D CSG renderer, written straight from docs/domains.md (3D CSG).

It shares no code with ``plad``: it reads the program text itself (prefix,
whitespace separated), evaluates each primitive's inside test at every voxel
center of the 32^3 grid in float64 with numpy, and combines recursively.
Used by the executor tests and as the baseline of ``bench.csg3d``.

Floating point is exact here: the cuboid test only halves integers. The
ellipsoid sum is a rational with denominator dividing dx^2 dy^2 dz^2 <= 31^6,
so when it is not exactly 1 it differs from 1 by at least 1 / 31^6 > 1e-9,
while float64 rounding moves it by about 1e-15: comparing with
``<= 1 + 1e-10`` decides every voxel as exact arithmetic would.
"""
from __future__ import annotations

import numpy as np

RES = 32
# voxel centers in index units, (32, 32, 32) each, indexed [x, y, z]
_P = np.indices((RES, RES, RES)).astype(np.float64)


def primitive(kind: str, x: int, y: int, z: int, dx: int, dy: int, dz: int) -> np.ndarray:
    c = np.array([x, y, z], dtype=np.float64)[:, None, None, None]
    d = np.array([dx, dy, dz], dtype=np.float64)[:, None, None, None]
    if kind == "cuboid":
        return (np.abs(_P - c) - d / 2).max(axis=0) <= 0
    if kind == "ellipsoid":
        return (((_P - c) / (d / 2)) ** 2).sum(axis=0) <= 1 + 1e-10
    raise ValueError(f"unknown primitive {kind!r}")


def render(text: str) -> np.ndarray:
    """Program text -> bool (32, 32, 32) [x, y, z]."""
    words = text.split()
    pos = 0

    def expr() -> np.ndarray:
        nonlocal pos
        word = words[pos]
        pos += 1
        if word in ("cuboid", "ellipsoid"):
            params = [int(v) for v in words[pos:pos + 6]]
            pos += 6
            return primitive(word, *params)
        a = expr()
        b = expr()
        if word == "union":
            return a | b
        if word == "inter":
            return a & b
        if word == "diff":
            return a & ~b
        raise ValueError(f"unknown token {word!r}")

    out = expr()
    assert pos == len(words), "trailing tokens"
    return out


def render_nodes(text: str) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """Every operator node of a program: (operator, result, first operand, second operand)."""
    words = text.split()
    pos = 0
    nodes = []

    def expr() -> np.ndarray:
        nonlocal pos
        word = words[pos]
        pos += 1
        if word in ("cuboid", "ellipsoid"):
            params = [int(v) for v in words[pos:pos + 6]]
            pos += 6
            return primitive(word, *params)
        a = expr()
        b = expr()
        out = {"union": a | b, "inter": a & b, "diff": a & ~b}[word]
        nodes.append((word, out, a, b))
        return out

    expr()
    return nodes
