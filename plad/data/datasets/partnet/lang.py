"""ShapeAssembly program text: the full hierarchical language -> checked statements.

The language is described in ``docs/shapeassembly.md`` ("Program text").
A program is a sequence of ``Assembly NAME { ... }`` blocks; the first is the
root, the others are sub-assemblies declared by a ``Program_K = Cuboid(...)``
line of their parent. Block lines are ``Cuboid``, ``attach``, ``squeeze``,
``reflect`` and ``translate`` statements.

Unlike the original (which dispatches on substrings, ignores unknown lines and
fails deep inside execution on a bad name), this parser checks everything it
can before execution and raises :class:`SAParseError`, a
:class:`~plad.domains.grammar.ProgramError` whose message is one line naming the line
number and the problem. Static checks include references: reflect/translate
copies get the names ``cube{N}`` (N = non-bbox cuboids of the block so far),
which can be computed from the text, so every name a statement uses is known
to exist before it runs. Blank lines are allowed (the original crashes on them).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

from plad.domains.grammar import ProgramError

FACES = ("right", "left", "top", "bot", "front", "back")
AXES = ("X", "Y", "Z")


class SAParseError(ProgramError):
    """A bad ShapeAssembly program; ``line`` is the 1-based line number (0 if none)."""

    def __init__(self, line: int, message: str):
        super().__init__(f"line {line}: {message}" if line else message, position=line or None)
        self.line = line


@dataclass(frozen=True)
class Stmt:
    """One executable statement.

    ``op``: ``cuboid`` (args: name, (l, h, w), aligned, is_sub), ``attach``
    (A, B, q1 (3,), q2 (3,)), ``squeeze`` (A, B, C, face, u, v), ``reflect``
    (A, axis index), ``translate`` (A, axis index, n, d). ``line`` is the
    1-based source line (0 for statements built from tokens).
    """

    op: str
    args: tuple
    line: int = 0


@dataclass
class Block:
    name: str
    stmts: list[Stmt] = field(default_factory=list)
    line: int = 0

    @property
    def bbox_dims(self) -> tuple[float, float, float]:
        return self.stmts[0].args[1]


@dataclass
class Program:
    """Blocks by name in text order; ``root`` is the first block's name."""

    blocks: dict[str, Block]
    root: str


_CALL = re.compile(r"^(?:(?P<lhs>[A-Za-z_][A-Za-z0-9_]*)\s*=\s*)?(?P<fn>[A-Za-z_]+)\s*\((?P<args>[^()]*)\)\s*$")
_ASSEMBLY = re.compile(r"^Assembly\s+(?P<name>[A-Za-z_][A-Za-z0-9_]*)\s*\{\s*$")
_ARITY = {"Cuboid": (3, 4), "attach": (8, 8), "squeeze": (6, 6), "reflect": (2, 2), "translate": (4, 4)}


#: the language's range of each kind of number (docs/shapeassembly.md, "Program text"): a shape is about one
#: unit across (PartNet's cuboids: 0.01 to 2.8), local coordinates address a cuboid's unit cube [0, 1]^3, a
#: translate distance is a fraction of the bbox, and its count makes that many copies (PartNet: at most 36).
#: Outside it execution fails numerically (1e300) or makes nothing (1e-300), silently.
DIM_RANGE = (1e-3, 1e3)
UNIT_RANGE = (0.0, 1.0)
DISTANCE_RANGE = (-1.0, 1.0)
MAX_COPIES = 100


def _float(text: str, what: str, line: int, lo: float, hi: float) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SAParseError(line, f"{what} must be a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise SAParseError(line, f"{what} must be finite, got {text!r}")
    if not lo <= value <= hi:
        raise SAParseError(line, f"{what} must be in [{lo:g}, {hi:g}] (the language's range), got {text}")
    return value


def _parse_line(text: str, line: int) -> Stmt:
    m = _CALL.match(text)
    if not m:
        raise SAParseError(line, f"cannot read {text!r}; expected NAME = Cuboid(...), attach(...), "
                                 f"squeeze(...), reflect(...), translate(...) or '}}'")
    fn, lhs = m.group("fn"), m.group("lhs")
    if fn not in _ARITY:
        raise SAParseError(line, f"unknown command {fn!r}; expected one of {', '.join(_ARITY)}")
    if (fn == "Cuboid") != (lhs is not None):
        raise SAParseError(line, "only Cuboid(...) is assigned to a name: write NAME = Cuboid(l, h, w, aligned)"
                           if fn == "Cuboid" else f"{fn}(...) does not take an assignment")
    args = [a.strip() for a in m.group("args").split(",")]
    lo, hi = _ARITY[fn]
    if not lo <= len(args) <= hi:
        want = f"{lo}" if lo == hi else f"{lo} or {hi}"
        raise SAParseError(line, f"{fn} expects {want} arguments, got {len(args)}")
    if fn == "Cuboid":
        for a in args[:3]:   # the sign first: "must be positive" says more than a range
            try:
                value = float(a)
            except ValueError:
                continue         # not a number: _float says so
            if value <= 0:
                raise SAParseError(line, f"dimensions of {lhs} must be positive, got {args[:3]}")
        dims = tuple(_float(a, f"{'lhw'[i]} of {lhs}", line, *DIM_RANGE) for i, a in enumerate(args[:3]))
        aligned = False
        if len(args) == 4:
            if args[3] not in ("True", "False"):
                raise SAParseError(line, f"aligned flag of {lhs} must be True or False, got {args[3]!r}")
            aligned = args[3] == "True"
        return Stmt("cuboid", (lhs, dims, aligned, "Program_" in lhs), line)
    if fn == "attach":
        q = tuple(_float(a, f"attach coordinate {i + 1}", line, *UNIT_RANGE) for i, a in enumerate(args[2:]))
        return Stmt("attach", (args[0], args[1], q[:3], q[3:]), line)
    if fn == "squeeze":
        if args[3] not in FACES:
            raise SAParseError(line, f"squeeze face must be one of {' '.join(FACES)}, got {args[3]!r}")
        u, v = (_float(a, "squeeze coordinate", line, *UNIT_RANGE) for a in args[4:])
        return Stmt("squeeze", (args[0], args[1], args[2], args[3], u, v), line)
    if args[1] not in AXES:
        raise SAParseError(line, f"{fn} axis must be X, Y or Z, got {args[1]!r}")
    axis = AXES.index(args[1])
    if fn == "reflect":
        return Stmt("reflect", (args[0], axis), line)
    try:
        n = int(args[2])
    except ValueError:
        raise SAParseError(line, f"translate count must be an integer, got {args[2]!r}") from None
    if not 1 <= n <= MAX_COPIES:
        raise SAParseError(line, f"translate count must be from 1 to {MAX_COPIES}, got {n}")
    return Stmt("translate", (args[0], axis, n, _float(args[3], "translate distance", line, *DISTANCE_RANGE)), line)


def check_block(block: Block) -> list[str]:
    """Check names in one block; returns the names of its sub-assembly declarations.

    Simulates only the naming: declarations add names, reflect adds ``cube{N}``,
    translate adds n of them.
    """
    stmts = block.stmts
    if not stmts or stmts[0].op != "cuboid" or stmts[0].args[0] != "bbox":
        raise SAParseError(stmts[0].line if stmts else block.line,
                           f"the first line of block {block.name} must declare bbox = Cuboid(l, h, w, aligned)")
    names = ["bbox"]
    known = {"bbox"}
    subs: list[str] = []

    def need(name: str, line: int, movable: bool = False) -> None:
        if name not in known:
            raise SAParseError(line, f"{name!r} is not a cuboid of block {block.name} at this point")
        if movable and name == "bbox":
            raise SAParseError(line, "the bbox cannot be moved or copied")

    for s in stmts:
        if s.op == "cuboid":
            name = s.args[0]
            if name not in known:
                known.add(name)
                names.append(name)
                if s.args[3]:
                    subs.append(name)
        elif s.op == "attach":
            need(s.args[0], s.line, movable=True)
            need(s.args[1], s.line)
            if s.args[0] == s.args[1]:
                raise SAParseError(s.line, f"cannot attach {s.args[0]} to itself")
        elif s.op == "squeeze":
            need(s.args[0], s.line, movable=True)
            need(s.args[1], s.line)
            need(s.args[2], s.line)
            if s.args[0] in (s.args[1], s.args[2]):
                raise SAParseError(s.line, f"cannot squeeze {s.args[0]} against itself")
        else:  # reflect / translate create copies named by the running count
            need(s.args[0], s.line, movable=True)
            for _ in range(1 if s.op == "reflect" else s.args[2]):
                copy = f"cube{len(names) - 1}"
                if copy not in known:
                    known.add(copy)
                    names.append(copy)
    return subs


def parse_program(text: str) -> Program:
    """Full-language program text -> :class:`Program`; raises :class:`SAParseError`."""
    blocks: dict[str, Block] = {}
    current: Block | None = None
    lines = text.splitlines()
    for number, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s:
            continue
        if current is None:
            m = _ASSEMBLY.match(s)
            if not m:
                raise SAParseError(number, f"expected 'Assembly NAME {{', got {s!r}")
            name = m.group("name")
            if name in blocks:
                raise SAParseError(number, f"block {name} is defined twice")
            current = Block(name, line=number)
            continue
        if s == "}":
            if not current.stmts:
                raise SAParseError(number, f"block {current.name} is empty; it needs at least its bbox line")
            blocks[current.name] = current
            current = None
            continue
        if s.startswith("Assembly"):
            raise SAParseError(number, f"block {current.name} (line {current.line}) is not closed before a new block")
        current.stmts.append(_parse_line(s, number))
    if current is not None:
        raise SAParseError(len(lines), f"block {current.name} (line {current.line}) is not closed with '}}'")
    if not blocks:
        raise SAParseError(0, "empty program: expected at least one 'Assembly NAME {' block")
    root = next(iter(blocks))
    # references between blocks: every declared sub-assembly has a block; no cycles
    children: dict[str, list[tuple[str, int]]] = {}
    for block in blocks.values():
        subs = check_block(block)
        children[block.name] = []
        for name in subs:
            line = next(s.line for s in block.stmts if s.op == "cuboid" and s.args[0] == name)
            if name not in blocks:
                raise SAParseError(line, f"sub-assembly {name} has no 'Assembly {name} {{' block")
            children[block.name].append((name, line))
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done

    def visit(name: str) -> None:
        state[name] = 1
        for child, line in children[name]:
            if state.get(child) == 1:
                raise SAParseError(line, f"sub-assembly {child} contains itself (cycle through {name})")
            if child not in state:
                visit(child)
        state[name] = 2

    visit(root)
    return Program(blocks, root)


def flat_program(stmts: list[Stmt]) -> Program:
    """A one-block program (the discretized variant) from statements."""
    block = Block("Program_0", list(stmts))
    check_block(block)
    return Program({block.name: block}, block.name)
