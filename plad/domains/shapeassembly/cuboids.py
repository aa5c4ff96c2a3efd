"""The cuboids of a token program: its statements run by the full language's executor.

Its own module so that the sampler (:mod:`.sampler`), which checks the cuboids of the programs it draws, and
the domain (the package) both use it without importing each other.

Speed: a search executes tens of thousands of programs that share most of their parts (an insertion appends a
part to a program it ran before, a rewrite changes one argument of one part). A part of a well-formed program
only creates its own cuboid and copies and never changes an earlier cuboid (it moves the cuboid it declares;
earlier cuboids and the bbox are only targets, and the attachment record a target would gain is only read by a
cuboid that moves again, so the executor runs with ``record_targets`` off), and the output rows are the
cuboids in declaration order. So the executor state after each part, and the part's
rows, depend only on the tokens up to the part's end: :func:`token_cuboids` keeps them for recent prefixes
(:data:`PREFIX_CACHE` of them) and runs only the parts after the longest prefix it has seen. A program whose
statements are not of that checked form (:func:`_checked`) runs as before, from scratch.
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from functools import lru_cache

import numpy as np

from plad.data.datasets.partnet.execute import F32, BlockState, ExecutionError, _place, execute_program
from plad.data.datasets.partnet.lang import Block, Program, Stmt
from plad.domains.shapeassembly.tokens import segment_statements, to_statements, token_table

#: prefixes (up to a part's end) whose executor state is kept, least recently used dropped first
PREFIX_CACHE = 16384


def _copy_name(parent: str, index: int | None) -> str:
    """PLAD's names for reflect / translate copies (never collide with cube0..cube9)."""
    return f"{parent}_ref" if index is None else f"{parent}_trans_{index}"


def token_cuboids(ids: Sequence[int]) -> np.ndarray:
    """Cuboids (n, 15) float32 of a valid token program (copies included), in the bbox frame.

    Raises :class:`~plad.data.datasets.partnet.execute.ExecutionError` if a
    frame becomes singular. Bit-identical to :func:`token_cuboids_plain` (it reuses the state of programs run
    before that share a prefix, see the module's docstring).
    """
    ids = [int(i) for i in ids]
    segments = _segments(tuple(ids))
    if segments is None:
        return token_cuboids_plain(ids)
    # the longest prefix of whole segments seen before: resume from its state
    keys = [tuple(ids[:end]) for end, _ in segments]
    done = len(keys)
    while done and keys[done - 1] not in _PREFIXES:
        done -= 1
    rows: list[np.ndarray] = []
    if done:
        snap = _PREFIXES[keys[done - 1]]
        _PREFIXES.move_to_end(keys[done - 1])
        if isinstance(snap, ExecutionError):
            raise snap.with_traceback(None)
        state = _resume(snap, segments[0][1][0])
        rows = list(snap.rows)
    else:
        state = _fresh(segments[0][1][0])
    root_dims = np.asarray(segments[0][1][0].args[1], dtype=F32)
    for i in range(done, len(segments)):
        before = len(state.cuboids)
        try:
            state.run(segments[i][1])
        except ExecutionError as err:
            _remember(keys[i], err)
            raise
        # the rows of this segment's cuboids, as execute_program places the leaves of a root block
        scale = (root_dims / state.cuboids["bbox"].dims).astype(F32)
        for c in list(state.cuboids.values())[max(before, 1):]:
            placed = _place(c, np.zeros(3, dtype=F32), _EYE, scale)
            rows.append(np.concatenate([placed[0], placed[1].reshape(-1), placed[2]]))
        _remember(keys[i], _Snapshot(state, rows))
    if not rows:
        return np.zeros((0, 15), dtype=F32)
    return np.stack(rows).astype(F32)


def token_cuboids_plain(ids: Sequence[int]) -> np.ndarray:
    """:func:`token_cuboids` from scratch: the program's statements as one block of the full language."""
    program = Program({"Program_0": Block("Program_0", to_statements(ids))}, "Program_0")
    return execute_program(program, copy_names=_copy_name)


def clear_cache() -> None:
    """Forget the kept prefixes (e.g. to time executions from scratch)."""
    _PREFIXES.clear()


_EYE = np.eye(3, dtype=F32)
_PREFIXES: OrderedDict[tuple[int, ...], _Snapshot | ExecutionError] = OrderedDict()


class _Snapshot:
    """The executor state after a prefix: its cuboids by name (shared with the states resumed from it: in the
    checked programs no later part changes an earlier cuboid, and with ``record_targets`` off an attach
    leaves its target untouched) and the rows so far."""

    __slots__ = ("cuboids", "rows")

    def __init__(self, state: BlockState, rows: list[np.ndarray]):
        self.cuboids = dict(state.cuboids)
        self.rows = tuple(rows)


def _fresh(first: Stmt) -> BlockState:
    """The executor of a token program before its statements (as execute_program makes it), leaving targets
    untouched (their records are only read by a cuboid that moves again, which no checked program has)."""
    return BlockState(first.args[1], first.args[2], _copy_name, record_targets=False)


def _resume(snap: _Snapshot, first: Stmt) -> BlockState:
    """A BlockState in the snapshot's state: its own dict of the same cuboid objects."""
    state = _fresh(first)
    state.cuboids = dict(snap.cuboids)
    return state


def _remember(key: tuple[int, ...], value) -> None:
    _PREFIXES[key] = value
    _PREFIXES.move_to_end(key)
    while len(_PREFIXES) > PREFIX_CACHE:
        _PREFIXES.popitem(last=False)


@lru_cache(maxsize=1)
def _special() -> tuple[int, int, int]:
    """The ids of ``Cuboid`` and ``END``, and the vocabulary size."""
    table = token_table()
    return table.index("Cuboid"), table.index("END"), len(table.tokens)


def _segments(ids: tuple[int, ...]) -> list[tuple[int, tuple[Stmt, ...]]] | None:
    """The program cut before each ``Cuboid`` and at its first ``END``: (end index, statements) per segment,
    the header (``START h``) first; None when the program is not of the form :func:`token_cuboids` may cache
    (then it runs from scratch, exactly as before)."""
    cuboid, end_id, n = _special()
    if not ids or min(ids) < 0 or max(ids) >= n:
        return None
    end = ids.index(end_id) if end_id in ids else len(ids)
    cuts = [0] + [i for i in range(end) if ids[i] == cuboid] + [end]
    out = []
    for j in range(len(cuts) - 1):
        stmts = _checked(ids[cuts[j]:cuts[j + 1]], j)
        if stmts is None:
            return None
        out.append((cuts[j + 1], stmts))
    return out


@lru_cache(maxsize=65536)
def _checked(tokens: tuple[int, ...], j: int) -> tuple[Stmt, ...] | None:
    """Statements of segment j read on their own (:func:`~.tokens.segment_statements`), if they are what a
    well-formed program's are: segment 0 declares the bbox and nothing else; segment j > 0 declares
    ``cube{j-1}``, then moves it to the bbox or earlier cuboids, then at most one Reflect or Translate of it,
    last. Read on its own, a segment whose statements reach past it fails to read (None), so these are also
    the statements that :func:`~.tokens.to_statements` makes of these tokens within the whole program."""
    try:
        stmts = segment_statements(tokens, max(j - 1, 0))
    except Exception:           # noqa: BLE001 - any reading failure: leave the program to the plain path
        return None
    if j == 0:
        ok = len(stmts) == 1 and stmts[0].op == "cuboid" and stmts[0].args[0] == "bbox"
        return tuple(stmts) if ok else None
    mover = f"cube{j - 1}"
    earlier = {"bbox"} | {f"cube{k}" for k in range(j - 1)}
    if not stmts or stmts[0].op != "cuboid" or stmts[0].args[0] != mover or stmts[0].args[3]:
        return None
    for k, s in enumerate(stmts[1:], 1):
        if s.args[0] != mover:
            return None
        if s.op == "attach" and s.args[1] in earlier:
            continue
        if s.op == "squeeze" and s.args[1] in earlier and s.args[2] in earlier:
            continue
        if s.op in ("reflect", "translate") and k == len(stmts) - 1:
            continue
        return None
    return tuple(stmts)
