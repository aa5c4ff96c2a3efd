"""The discretized, non-hierarchical ShapeAssembly of PLAD: tokens and text.

The rules: docs/shapeassembly.md, "The discretized language of the domain".

A program is one flat block::

    START h  (Cuboid l h w  MOVES  [SYM])+  END

with ``MOVES`` one of ``Attach cind face fpos fpos``, two such Attaches, or
``Squeeze cind cind face fpos``, and ``SYM`` one of ``Reflect axis`` or
``Translate axis snum n``. Every Attach/Squeeze/Reflect/Translate applies to
the most recently declared cuboid. Number tokens ``1``..``31`` mean i/32
(``START h`` declares ``bbox = Cuboid(1, h/32, 1)``); ``fpos_i_j`` is the
in-face point (i/10, j/10); ``snum_k`` is the copy count; ``cind`` is ``bbox``
or ``cube0``..``cube9`` (declaration order). At most 10 cuboids are declared
and a program has at most 100 tokens, END included.

The text form is the tokens separated by whitespace, e.g.
``START 20 Cuboid 30 2 30 Attach bbox top fpos_5_5 fpos_5_5 END``.

Grammar as data (:mod:`plad.domains.grammar`): the stack symbols carry the number c
of cuboids declared so far, so that a reference ``cube_j`` is only allowed
when cuboid j exists and is not the one being moved, and a tenth Cuboid is
the last. Symbols: ``P{c}`` next part or END; ``M{c}`` the moves of cuboid c
(just declared); ``A{c}`` after its first Attach (a second Attach, a symmetry,
the next part or END); ``Z{c}`` after its moves (a symmetry, the next part or
END); ``C{m}`` a cuboid reference made by mover m; ``N``, ``face``, ``fpos``,
``axis``, ``snum`` arguments. Tokens that depend on c have one rule per c.
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

from plad.data.datasets.partnet.lang import AXES, FACES, Stmt
from plad.domains.grammar import ProgramError, Token, TokenTable

RES = 32
MAX_CUBOIDS = 10
MAX_COPIES = 4
MAX_LEN = 100
FPOS = range(1, 10)
# face order of PLAD's vocabulary (token order only; semantics are by name)
FACE_TOKENS = ("left", "right", "bot", "top", "back", "front")


def _after_part(c: int) -> list[str]:
    """Symbols after which cuboid c's part may be complete (c cuboids declared)."""
    return [f"A{c}", f"Z{c}"] + ([f"P{c}"] if c else [])


@lru_cache(maxsize=1)
def token_table() -> TokenTable:
    def rules(pairs):
        pairs = list(pairs)
        return dict(pops=pairs[0][0], pushes=pairs[0][1], alt=tuple(pairs[1:]))

    t: list[Token] = [
        Token("START", pops=("S",), pushes=("P0", "N"), kind="start"),
        Token("END", stop=True, kind="end",
              **rules(((s,), ()) for c in range(1, MAX_CUBOIDS + 1) for s in _after_part(c))),
        # Cuboid l h w declares cuboid c; then its moves (M{c}) and later symbols
        Token("Cuboid", kind="cuboid",
              **rules(((s,), (f"M{c}", "N", "N", "N")) for c in range(MAX_CUBOIDS)
                      for s in ([f"P{c}"] + ([f"A{c}", f"Z{c}"] if c else [])))),
        # first Attach of cuboid c (M{c}) or its second one (A{c+1})
        Token("Attach", kind="attach", **rules(
            [((f"M{c}",), (f"A{c + 1}", "fpos", "fpos", "face", f"C{c}")) for c in range(MAX_CUBOIDS)]
            + [((f"A{c + 1}",), (f"Z{c + 1}", "fpos", "fpos", "face", f"C{c}")) for c in range(MAX_CUBOIDS)])),
        Token("Squeeze", kind="squeeze", **rules(
            ((f"M{c}",), (f"Z{c + 1}", "fpos", "face", f"C{c}", f"C{c}")) for c in range(MAX_CUBOIDS))),
        Token("Reflect", kind="reflect", **rules(
            ((s,), (f"P{c}", "axis")) for c in range(1, MAX_CUBOIDS + 1) for s in (f"A{c}", f"Z{c}"))),
        Token("Translate", kind="translate", **rules(
            ((s,), (f"P{c}", "N", "snum", "axis")) for c in range(1, MAX_CUBOIDS + 1) for s in (f"A{c}", f"Z{c}"))),
    ]
    t += [Token(str(i), pops=("N",), kind="num", params=(i,)) for i in range(1, RES)]
    t.append(Token("bbox", kind="cind", params=(-1,), **rules(((f"C{m}",), ()) for m in range(MAX_CUBOIDS))))
    t += [Token(f"cube{j}", kind="cind", params=(j,), **rules(((f"C{m}",), ()) for m in range(j + 1, MAX_CUBOIDS)))
          for j in range(MAX_CUBOIDS - 1)]
    t += [Token(f, pops=("face",), kind="face", params=(f,)) for f in FACE_TOKENS]
    t += [Token(f"fpos_{i}_{j}", pops=("fpos",), kind="fpos", params=(i, j)) for i in FPOS for j in FPOS]
    t += [Token(a, pops=("axis",), kind="axis", params=(AXES.index(a),)) for a in AXES]
    t += [Token(f"snum_{k}", pops=("snum",), kind="snum", params=(k,)) for k in range(1, MAX_COPIES + 1)]
    return TokenTable(tuple(t), start=("S",), max_len=MAX_LEN)


def parse(text: str) -> list[int]:
    """Whitespace-separated token text -> ids; a missing final END is added.

    Raises :class:`ProgramError` naming the bad token.
    """
    table = token_table()
    words = text.split()
    if not words:
        raise ProgramError("empty program: expected START h Cuboid ... END", position=0)
    ids = []
    for pos, w in enumerate(words):
        if not table.has(w):
            raise ProgramError(f"token {pos} {w!r} is not a ShapeAssembly token", position=pos, token=w)
        ids.append(table.index(w))
    if words[-1] != "END":
        ids.append(table.index("END"))
    table.check(ids)
    return ids


def format_program(ids: Sequence[int]) -> str:
    table = token_table()
    out = []
    for i in ids:
        name = table.tokens[int(i)].name
        out.append(name)
        if name == "END":
            break
    return " ".join(out)


def _cind(j: int) -> str:
    return "bbox" if j < 0 else f"cube{j}"


def attach_points(face: str, to_bbox: bool, mover_uv: tuple[float, float],
                  target_uv: tuple[float, float]) -> tuple[list[float], list[float]]:
    """Local points (mover q1, target q2) of ``Attach cind face fpos fpos`` (docs/shapeassembly.md).

    The mover's coordinate on the face axis is 1 for right/top/front and 0
    otherwise; the target uses the opposite side, except the bbox with top/bot
    (same side, from inside). The fpos give the two remaining coordinates in
    increasing axis order.
    """
    axis = FACES.index(face) // 2
    side = 1.0 if face in ("right", "top", "front") else 0.0
    other = side if (to_bbox and face in ("top", "bot")) else 1.0 - side
    q1, q2 = [0.0] * 3, [0.0] * 3
    q1[axis], q2[axis] = side, other
    rest = [a for a in range(3) if a != axis]
    for a, x, y in zip(rest, mover_uv, target_uv):
        q1[a], q2[a] = x, y
    return q1, q2


def to_statements(ids: Sequence[int]) -> list[Stmt]:
    """Token ids of a valid program -> statements of the equivalent one-block program."""
    return segment_statements(ids, 0)


def segment_statements(ids: Sequence[int], count: int) -> list[Stmt]:
    """Statements of the tokens ``ids``, read as :func:`to_statements` reads a program, with ``count`` cuboids
    declared before them (the part of a program from one ``Cuboid`` to the next: count = the part's index)."""
    table = token_table()
    toks = [table.tokens[int(i)] for i in ids]
    stmts: list[Stmt] = []
    pos = 0

    def args(n: int) -> list:
        nonlocal pos
        out = [toks[pos + 1 + k].params for k in range(n)]
        pos += 1 + n
        return out

    while pos < len(toks):
        kind = toks[pos].kind
        mover = f"cube{count - 1}"
        if kind == "start":
            (h,), = args(1)
            stmts.append(Stmt("cuboid", ("bbox", (1.0, h / RES, 1.0), False, False)))
        elif kind == "cuboid":
            dims = tuple(p[0] / RES for p in args(3))
            stmts.append(Stmt("cuboid", (f"cube{count}", dims, False, False)))
            count += 1
        elif kind == "attach":
            (j,), (face,), uv1, uv2 = args(4)
            q1, q2 = attach_points(face, j < 0, (uv1[0] / 10, uv1[1] / 10), (uv2[0] / 10, uv2[1] / 10))
            stmts.append(Stmt("attach", (mover, _cind(j), tuple(q1), tuple(q2))))
        elif kind == "squeeze":
            (j1,), (j2,), (face,), uv = args(4)
            stmts.append(Stmt("squeeze", (mover, _cind(j1), _cind(j2), face, uv[0] / 10, uv[1] / 10)))
        elif kind == "reflect":
            (axis,), = args(1)
            stmts.append(Stmt("reflect", (mover, axis)))
        elif kind == "translate":
            (axis,), (n,), (d,) = args(3)
            stmts.append(Stmt("translate", (mover, axis, n, d / RES)))
        elif kind == "end":
            break
        else:
            raise ProgramError(f"token {pos} {toks[pos].name!r} cannot start a statement", position=pos)
    return stmts
