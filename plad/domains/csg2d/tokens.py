"""2D CSG (CSGNet) vocabulary, grammar and text form.

Vocabulary rule (documented, checked by a test against CSGNet's 396 draw
tokens): every combination of kind in {circle ``c``, square ``s``, triangle
``t``}, x and y in {8, 16, ..., 56} and r in {8, 12, ..., 32} whose primitive,
rendered by CSGNet's pixel rules (docs/domains.md, "Rendering") without
clipping, is non-empty and lies entirely inside the 64 x 64 canvas. That
gives 424 draw tokens (CSGNet keeps 396 of them), then the operators ``+``
(union), ``*`` (intersection), ``-`` (difference) and the stop token ``$``.

Programs are postfix; see :mod:`plad.domains.grammar` for how the stack machine
(``shape`` symbols) makes the grammar data.
"""
from __future__ import annotations

import re
from functools import lru_cache

import numpy as np
from skimage import draw

from plad.domains.grammar import ProgramError, Token, TokenTable

CANVAS = 64
KINDS = ("c", "s", "t")
KIND_NAMES = {"c": "circle", "s": "square", "t": "triangle"}
XY_VALUES = tuple(range(8, 57, 8))
R_VALUES = tuple(range(8, 33, 4))
OPERATORS = {"+": "union", "*": "intersection", "-": "difference"}
STOP = "$"
#: At most 13 tokens before ``$`` (7 primitives, 6 operators), as in the paper.
MAX_LEN = 14
SHAPE = "shape"  # the one grammar symbol: a finished sub-shape on the stack


def primitive_pixels(kind: str, x: int, y: int, r: int, clip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a primitive's pixels by CSGNet's renderer (row = y, col = x).

    With ``clip=False`` the coordinates may fall outside the canvas (used by the
    vocabulary rule).
    """
    shape = (CANVAS, CANVAS) if clip else None
    if kind == "c":
        # strictly inside distance r of the center
        return draw.disk((y, x), r, shape=shape)
    if kind == "s":
        side = 1.412 * r
        lo_r, hi_r = int(y - side / 2), int(y + side / 2)
        lo_c, hi_c = int(x - side / 2), int(x + side / 2)
        rows = np.array([lo_r, hi_r, hi_r, lo_r])
        cols = np.array([hi_c, hi_c, lo_c, lo_c])
    elif kind == "t":
        length = 1.732 * r
        base, apex = int(y + length / (2 * 1.732)), int(y - length / 1.732)
        rows = np.array([base, base, apex])
        cols = np.array([int(x - length / 2), int(x + length / 2), x])
    else:
        raise ValueError(f"unknown primitive kind {kind!r}")
    r1, c1 = draw.polygon(rows, cols, shape=shape)
    r2, c2 = draw.polygon_perimeter(rows, cols, shape=shape)
    return np.concatenate([r1, r2]), np.concatenate([c1, c2])


def render_primitive(kind: str, x: int, y: int, r: int) -> np.ndarray:
    canvas = np.zeros((CANVAS, CANVAS), dtype=bool)
    rr, cc = primitive_pixels(kind, x, y, r)
    canvas[rr, cc] = True
    return canvas


def _in_vocabulary(kind: str, x: int, y: int, r: int) -> bool:
    rr, cc = primitive_pixels(kind, x, y, r, clip=False)
    return len(rr) > 0 and rr.min() >= 0 and cc.min() >= 0 and rr.max() < CANVAS and cc.max() < CANVAS


def draw_name(kind: str, x: int, y: int, r: int) -> str:
    return f"{kind}({x},{y},{r})"


@lru_cache(maxsize=1)
def token_table() -> TokenTable:
    tokens: list[Token] = []
    for kind in KINDS:
        for x in XY_VALUES:
            for y in XY_VALUES:
                for r in R_VALUES:
                    if _in_vocabulary(kind, x, y, r):
                        tokens.append(Token(draw_name(kind, x, y, r), pops=(), pushes=(SHAPE,),
                                            kind="draw", params=(kind, x, y, r)))
    for sym, op in OPERATORS.items():
        tokens.append(Token(sym, pops=(SHAPE, SHAPE), pushes=(SHAPE,), kind=op))
    tokens.append(Token(STOP, pops=(SHAPE,), pushes=(), stop=True, kind="stop"))
    return TokenTable(tuple(tokens), start=(), max_len=MAX_LEN)


_DRAW_RE = re.compile(r"([A-Za-z])\s*\(\s*([^(),]*?)\s*,\s*([^(),]*?)\s*,\s*([^(),]*?)\s*\)")
_INT_RE = re.compile(r"[+-]?\d+")


def parse(text: str) -> list[int]:
    """CSGNet text (``c(32,24,16)s(40,40,12)+$``) -> token ids; whitespace between tokens is allowed.

    A missing final ``$`` is added. Raises :class:`ProgramError` naming the bad token.
    """
    table = token_table()
    ids: list[int] = []
    names: list[str] = []
    pos = 0
    while pos < len(text):
        if text[pos].isspace():
            pos += 1
            continue
        index = len(ids)
        ch = text[pos]
        if ch in OPERATORS or ch == STOP:
            ids.append(table.index(ch))
            names.append(ch)
            pos += 1
            continue
        m = _DRAW_RE.match(text, pos)
        if not m:
            snippet = text[pos:pos + 12]
            raise ProgramError(
                f"token {index} at character {pos}: cannot read {snippet!r}; expected a draw token "
                f"like c(32,32,16) or one of + * - $", position=index, token=snippet)
        kind, *args = m.groups()
        if kind not in KINDS:
            raise ProgramError(f"token {index} {m.group(0)!r}: unknown primitive {kind!r} "
                               f"(c circle, s square, t triangle)", position=index, token=m.group(0))
        if not all(_INT_RE.fullmatch(a) for a in args):
            raise ProgramError(f"token {index} {m.group(0)!r}: parameters must be integers",
                               position=index, token=m.group(0))
        x, y, r = (int(a) for a in args)
        name = draw_name(kind, x, y, r)
        if not table.has(name):
            raise ProgramError(
                f"token {index} {name!r} is not in the vocabulary: x and y must be in 8..56 step 8, "
                f"r in 8..32 step 4, and the {KIND_NAMES[kind]} must lie inside the 64x64 canvas",
                position=index, token=name)
        ids.append(table.index(name))
        names.append(name)
        pos = m.end()
    if not ids:
        raise ProgramError("empty program", position=0)
    if names[-1] != STOP:
        ids.append(table.index(STOP))
    table.check(ids)
    return ids


def format_program(ids) -> str:
    table = token_table()
    out = []
    for i in ids:
        name = table.tokens[int(i)].name
        out.append(name)
        if name == STOP:
            break
    return "".join(out)
