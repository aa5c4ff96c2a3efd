"""SVG of a 2D CSG program: its primitives as vector shapes, its operations as SVG masks.

Coordinates are the canvas' pixel units: pixel (row, col) covers
[col, col + 1] x [row, row + 1], so the SVG's 64 x 64 view box is the canvas.
Primitives are drawn as the geometric shapes behind CSGNet's pixel renderer
(docs/domains.md, "Rendering"): a circle of radius r around the pixel center (x, y), the
square and the triangle through the corner pixels it fills.

Every operation is representable. Union draws both operands; intersection
draws the first operand through a mask holding the second. Difference is the
intersection with the complement of the second operand, and complements are
pushed down to the primitives by De Morgan's laws (the complement of a
primitive is the canvas with the primitive cut out, an even-odd path). Mask
contents are therefore always opaque white, so renderers that read masks by
luminance (the SVG standard) and those that read only their alpha (cairo)
draw the same shape. The shape is black on a white background, like the
canvases.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from plad.domains.csg2d.tokens import CANVAS, format_program, token_table


def _outline(kind: str, x: int, y: int, r: int) -> str:
    """Path data of a primitive's outline."""
    if kind == "c":
        cx, cy = x + 0.5, y + 0.5
        return f"M{cx - r:g},{cy:g}a{r},{r} 0 1,0 {2 * r},0a{r},{r} 0 1,0 {-2 * r},0Z"
    if kind == "s":
        side = 1.412 * r
        lo_r, hi_r = int(y - side / 2), int(y + side / 2)
        lo_c, hi_c = int(x - side / 2), int(x + side / 2)
        return f"M{lo_c},{lo_r}H{hi_c + 1}V{hi_r + 1}H{lo_c}Z"
    length = 1.732 * r
    base, apex = int(y + length / (2 * 1.732)), int(y - length / 1.732)
    left, right = int(x - length / 2), int(x + length / 2)
    # the polygon through the corner pixels' centers, its edges moved half a pixel outwards: the
    # filled polygon plus its one-pixel perimeter (differs from the bitmap by ~5 edge pixels)
    corners = np.array([[left, base], [right, base], [x, apex]], dtype=np.float64) + 0.5
    center = corners.mean(0)
    lines = []
    for i in range(3):
        a, b = corners[i], corners[(i + 1) % 3]
        normal = np.array([b[1] - a[1], a[0] - b[0]]) / np.hypot(*(b - a))
        if np.dot(normal, a - center) < 0:
            normal = -normal
        lines.append((a + 0.5 * normal, b - a))
    points = []
    for (p1, t1), (p2, t2) in zip(lines[-1:] + lines[:-1], lines):   # corner i: edges i-1 and i
        s = np.linalg.solve(np.array([t1, -t2]).T, p2 - p1)
        points.append(p1 + s[0] * t1)
    return "M" + "L".join(f"{px:.3f},{py:.3f}" for px, py in points) + "Z"


def _tree(ids: Sequence[int]):
    """Postfix ids -> nested tuples: ``("draw", params)`` or ``(kind, A, B)``."""
    table = token_table()
    stack: list = []
    for i in ids:
        tok = table.tokens[int(i)]
        if tok.stop:
            break
        if tok.kind == "draw":
            stack.append(("draw", tok.params))
        else:
            b, a = stack.pop(), stack.pop()
            stack.append((tok.kind, a, b))
    if len(stack) != 1:
        raise ValueError("not a complete csg2d program")
    return stack[0]


def to_svg(ids: Sequence[int]) -> str:
    """An SVG document drawing the shape of a valid csg2d program."""
    box = f'x="0" y="0" width="{CANVAS}" height="{CANVAS}"'
    masks: list[str] = []

    def union(a: str, b: str) -> str:
        return f"<g>{a}{b}</g>"

    def inter(a: str, b: str) -> str:
        mid = f"m{len(masks)}"
        masks.append(f'<mask id="{mid}" maskUnits="userSpaceOnUse" {box}><g fill="white">{b}</g></mask>')
        return f'<g mask="url(#{mid})">{a}</g>'

    def emit(node, positive: bool) -> str:
        """Fragment drawing the node's shape (``positive``) or its complement in the canvas."""
        if node[0] == "draw":
            if positive:
                return f'<path d="{_outline(*node[1])}"/>'
            return f'<path fill-rule="evenodd" d="M0,0H{CANVAS}V{CANVAS}H0Z{_outline(*node[1])}"/>'
        kind, a, b = node
        if kind == "union":          # not(A or B) = not A and not B
            return union(emit(a, True), emit(b, True)) if positive else inter(emit(a, False), emit(b, False))
        if kind == "intersection":   # not(A and B) = not A or not B
            return inter(emit(a, True), emit(b, True)) if positive else union(emit(a, False), emit(b, False))
        # difference A and not B; not(A and not B) = not A or B
        return inter(emit(a, True), emit(b, False)) if positive else union(emit(a, False), emit(b, True))

    body = emit(_tree(ids), True)
    return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {CANVAS} {CANVAS}" '
            f'width="{CANVAS * 4}" height="{CANVAS * 4}">\n'
            f"  <title>{format_program(ids)}</title>\n"
            f"  <defs>{''.join(masks)}</defs>\n"
            f'  <rect {box} fill="white"/>\n'
            f'  <g fill="black">{body}</g>\n'
            "</svg>\n")
