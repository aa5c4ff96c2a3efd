"""3D CSG vocabulary, grammar and text form (docs/domains.md, paper supplement).

A program is prefix notation over a 32^3 voxel grid::

    E -> union E E | inter E E | diff E E | cuboid N N N N N N | ellipsoid N N N N N N
    N -> 1 | 2 | ... | 31

``diff A B`` is A AND NOT B. The six integers of a primitive are, in voxel
index units, its center (x, y, z) and then its full extents (dx, dy, dz).

Vocabulary (36 domain tokens): ``cuboid``,
``ellipsoid``, ``union``, ``inter``, ``diff``, then ``1`` .. ``31``. The
paper's ``start`` token is the model's own input-only BOS token
(:class:`plad.model.network.ModelConfig.bos`), which every domain gets; it is never
predicted, so it is not a domain token. There is no end token: a program is
complete when no argument is still open, which the stack machine expresses
directly (start stack ``[shape]``; an operator pops ``shape`` and pushes
``shape shape``, a primitive pops ``shape`` and pushes six ``num``, an
integer pops ``num``). The length cap is 100 program tokens.

The text form is the tokens separated by whitespace (newlines and
indentation allowed), e.g. ``diff cuboid 16 16 16 20 20 20 ellipsoid 16 16 16 12 12 30``.
The paper's names ``intersect``/``subtract`` (and ``intersection``/
``difference``) are accepted as aliases of ``inter``/``diff``.
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

from plad.domains.grammar import ProgramError, Token, TokenTable

RES = 32
MAX_LEN = 100
PRIMITIVES = ("cuboid", "ellipsoid")
OPERATORS = ("union", "inter", "diff")
N_PARAMS = 6
PARAM_MIN, PARAM_MAX = 1, RES - 1
ALIASES = {"intersect": "inter", "intersection": "inter", "subtract": "diff", "difference": "diff"}
SHAPE, NUM = "shape", "num"  # grammar symbols: a shape still expected, a parameter still expected


@lru_cache(maxsize=1)
def token_table() -> TokenTable:
    tokens = [Token(p, pops=(SHAPE,), pushes=(NUM,) * N_PARAMS, kind="primitive", params=(p,))
              for p in PRIMITIVES]
    tokens += [Token(o, pops=(SHAPE,), pushes=(SHAPE, SHAPE), kind="operator", params=(o,)) for o in OPERATORS]
    tokens += [Token(str(i), pops=(NUM,), kind="num", params=(i,)) for i in range(PARAM_MIN, PARAM_MAX + 1)]
    return TokenTable(tuple(tokens), start=(SHAPE,), max_len=MAX_LEN)


def _describe(open_items: list[tuple[str, int, int]]) -> str:
    """What the innermost open item still needs, for error messages."""
    name, pos, have = open_items[-1]
    if name in PRIMITIVES:
        return f"{name} at token {pos} has {have} of its {N_PARAMS} parameters"
    return f"{name} at token {pos} is missing its {'first' if have == 0 else 'second'} operand"


def parse(text: str) -> list[int]:
    """Program text -> token ids. Raises :class:`ProgramError` (one line) naming the bad token."""
    table = token_table()
    words = text.split()
    if not words:
        raise ProgramError("empty program", position=0)
    ids: list[int] = []
    # open items, innermost last: (name, token position, arguments received so far);
    # an empty list before the first token means "a shape is expected".
    open_items: list[tuple[str, int, int]] = []
    for pos, word in enumerate(words):
        if pos > 0 and not open_items:
            raise ProgramError(f"token {pos} {word!r} comes after the program is already complete "
                               f"(a program is one shape expression)", position=pos, token=word)
        if pos >= MAX_LEN:
            raise ProgramError(f"program has {len(words)} tokens; the length cap is {MAX_LEN}",
                               position=pos, token=word)
        name = ALIASES.get(word.lower(), word.lower())
        wants_param = bool(open_items) and open_items[-1][0] in PRIMITIVES
        if name in PRIMITIVES or name in OPERATORS:
            if wants_param:
                raise ProgramError(f"token {pos} {word!r}: expected an integer parameter, but "
                                   f"{_describe(open_items)}", position=pos, token=word)
        elif word.lstrip("+-").isdigit():
            if not wants_param:
                where = f" ({_describe(open_items)})" if open_items else ""
                raise ProgramError(f"token {pos} {word!r}: expected a shape (cuboid, ellipsoid, union, inter "
                                   f"or diff), got a number{where}", position=pos, token=word)
            if not PARAM_MIN <= int(word) <= PARAM_MAX:
                raise ProgramError(f"token {pos} {word!r}: parameters are integers {PARAM_MIN}..{PARAM_MAX} "
                                   f"(voxel units on the {RES}^3 grid)", position=pos, token=word)
            name = str(int(word))
        else:
            raise ProgramError(f"token {pos} {word!r} is not a csg3d token; expected cuboid, ellipsoid, union, "
                               f"inter, diff or an integer {PARAM_MIN}..{PARAM_MAX}", position=pos, token=word)
        ids.append(table.index(name))
        # this token fills one argument of the innermost open item ...
        if open_items:
            item_name, item_pos, have = open_items[-1]
            open_items[-1] = (item_name, item_pos, have + 1)
        # ... and opens a new item if it takes arguments
        if name in PRIMITIVES or name in OPERATORS:
            open_items.append((name, pos, 0))
        # close every item that has all its arguments (a closing one fills its parent's slot,
        # which was already counted when the item was opened)
        while open_items and open_items[-1][2] == (N_PARAMS if open_items[-1][0] in PRIMITIVES else 2):
            open_items.pop()
    if open_items:
        raise ProgramError(f"program is incomplete: {_describe(open_items)}", position=len(words))
    table.check(ids)  # the grammar table must agree with the hand-written reader
    return ids


def format_program(ids: Sequence[int]) -> str:
    """Token ids -> text (whitespace separated), stopping where the program is complete."""
    table = token_table()
    out, need = [], 1  # open argument counter: programs end when it reaches zero
    for i in ids:
        t = table.tokens[int(i)]
        out.append(t.name)
        need += {"primitive": N_PARAMS - 1, "operator": 1, "num": -1}[t.kind]
        if need == 0:
            break
    return " ".join(out)


def program_tree(ids: Sequence[int]):
    """Nested tuples of a valid program: ``("cuboid", (x, y, z, dx, dy, dz))`` or ``(op, A, B)``."""
    table = token_table()
    names = [table.tokens[int(i)].name for i in ids]
    pos = 0

    def node():
        nonlocal pos
        name = names[pos]
        pos += 1
        if name in PRIMITIVES:
            params = tuple(int(n) for n in names[pos:pos + N_PARAMS])
            pos += N_PARAMS
            return (name, params)
        a = node()
        return (name, a, node())

    return node()
