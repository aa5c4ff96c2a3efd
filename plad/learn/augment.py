"""An unlimited stream of (shape, program) pairs near the real distribution: symmetries and edits of labels.

Given a domain's labelled programs (valid token programs of real shapes), every call draws new programs
from them and executes them, so each pair's program executes exactly to its shape:

* **symmetries** (:meth:`plad.domains.base.Domain.symmetries`): maps the grammar can express, e.g. a
  mirror or a quarter turn of the grid, each a program -> program map whose execution is the transformed
  shape (the domain's module says where rasterization or rounding makes that approximate). None where the grammar cannot
  express the image: the program then stays as it is;
* **edits**, generic through the domain's rewrite space (:class:`plad.domains.space.RewriteSpace`):

  - ``jitter``: one parameter token moved to a neighbouring value of the same kind (a local PO move of
    :meth:`~plad.domains.space.RewriteSpace.blocks` to a token of the same kind, never of a boolean
    operator: a number +-1 or +-2, an in-face point one step; a 2D draw token one grid step, or another
    primitive at the same place; a 3D primitive's type);
  - ``drop``: one primitive (or part) removed (:meth:`~plad.domains.space.RewriteSpace.removals`);
  - ``graft``: a sub-expression (not the whole program) replaced by a sub-expression of another label
    (:meth:`~plad.domains.space.RewriteSpace.nodes`, ``standalone``, ``splice``), within the length cap;
    for a domain without an expression tree, the domain's own ``graft`` (:meth:`Domain.edits`) or none.

  A domain's :meth:`~plad.domains.base.Domain.edits` adds edits or replaces a generic one of the same
  name. Every edit returns a valid program within the length cap, or None.

:func:`transformed` draws, per program, a symmetry (identity included) with probability
``symmetry_share`` and then an edit with probability ``edit_share``; :func:`pairs` executes the result,
and where that left an empty shape (e.g. a difference that removes everything, or a ShapeAssembly
program whose frame became singular) takes the program before the edit, or the original, instead.
Everything is driven by the numpy generator given, so a fixed seed gives the same stream. The programs
are not canonicalized: where training wants canonical labels, ``domain.canonical`` (the same execution)
is the caller's step.

Cost of :func:`pairs` for a batch of 64 sampled programs with the default shares, one torch thread, on
our 2-core machine while two label searches kept both cores busy (median of 20 batches, 10 for
ShapeAssembly; transforms, execution and the executions of the fallbacks): 2D CSG 11 ms (5.4 ms the
fastest batch; the transforms alone 2.1 ms), 3D CSG 30 ms with the paper sampler's programs (56 tokens on
average) and 25 ms with the parts sampler's (the transforms 10 ms); ShapeAssembly 148 ms with the paper
sampler's programs and 85 ms with the inside sampler's, nearly all of it its executor (a Python
interpreter of the statements), the transforms 5 ms. Two torch threads on the busy machine made the 3D
executor 10 to 50 times slower: a data stream beside training should run with one.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from plad.domains.base import Domain, Edit, Symmetry, pad_programs
from plad.domains.grammar import ProgramError

#: the generic edits, in the order their names are drawn from
GENERIC = ("jitter", "drop", "graft")


def symmetries_of(domain: Domain, names: Sequence[str] | None = None) -> tuple[Symmetry, ...]:
    """The domain's symmetries, or those of ``names`` (a ``KeyError`` names an unknown one)."""
    offered = {s.name: s for s in domain.symmetries()}
    if names is None:
        return tuple(offered.values())
    unknown = [n for n in names if n not in offered]
    if unknown:
        raise KeyError(f"{domain.name} has no symmetry {', '.join(unknown)}; it offers {', '.join(offered) or 'none'}")
    return tuple(offered[n] for n in names)


def valid(domain: Domain, program: Sequence[int] | None) -> list[int] | None:
    """``program`` as a list if it is a complete valid program within the length cap, else None (the full
    grammar check, ~1 ms for a 100-token program; the stream itself relies on the moves' contracts)."""
    program = _fits(domain, program)
    if program is None:
        return None
    try:
        domain.check(program)
    except ProgramError:
        return None
    return program


def _fits(domain: Domain, program: Sequence[int] | None) -> list[int] | None:
    """``program`` as a list if it is non-empty and within the length cap, else None.

    Symmetries and edits make valid programs by construction (a :class:`Symmetry` maps valid programs to
    valid ones; the rewrite space's PO substitutions, removals and splices of sub-expressions give valid
    programs), which tests/plad/learn/test_augment.py checks on thousands of each; only the length cap is
    checked here, as grafting can exceed it.
    """
    if program is None or not 0 < len(program) <= domain.tokens.max_len:
        return None
    return [int(t) for t in program]


# ---- generic edits --------------------------------------------------------------------------------
def _operator_positions(domain: Domain, program: Sequence[int]) -> set[int]:
    """Token positions of the boolean operators: the tokens of a node with children outside its children."""
    out: set[int] = set()
    nodes = domain.rewrite.nodes(program)
    for node in nodes:
        if node.boolean:
            inside = set(range(node.start, node.end))
            for c in node.children:
                inside -= set(range(nodes[c].start, nodes[c].end))
            out |= inside
    return out


def jitter(domain: Domain, program: Sequence[int], donors: Sequence[Sequence[int]],
           rng: np.random.Generator) -> list[int] | None:
    """One parameter token moved to a neighbouring value of its kind (a local PO move of the rewrite space): a
    token drawn among those with such a move, then one of its moves."""
    space = domain.rewrite
    if space is None:
        return None
    kinds = [t.kind for t in domain.tokens.tokens]
    operators = _operator_positions(domain, program)
    slots = []
    for block in space.blocks(program, wide=False):
        for slot in block:
            if slot.position not in operators:
                same = [c for c in slot.choices if kinds[c] == kinds[program[slot.position]]]
                if same:
                    slots.append((slot.position, same))
    if not slots:
        return None
    pos, same = slots[int(rng.integers(len(slots)))]
    token = same[int(rng.integers(len(same)))]
    out = list(program)
    out[pos] = token
    return _fits(domain, out)


def drop(domain: Domain, program: Sequence[int], donors: Sequence[Sequence[int]],
         rng: np.random.Generator) -> list[int] | None:
    """The program without one of its primitives (or parts): one of the rewrite space's removals."""
    if domain.rewrite is None:
        return None
    shorter = domain.rewrite.removals(list(program))
    return _fits(domain, shorter[int(rng.integers(len(shorter)))]) if shorter else None


def graft(domain: Domain, program: Sequence[int], donors: Sequence[Sequence[int]],
          rng: np.random.Generator) -> list[int] | None:
    """A sub-expression of the program (not all of it) replaced by one of a donor drawn from ``donors``,
    the result within the length cap; None for a domain without an expression tree."""
    space = domain.rewrite
    if space is None or not donors:
        return None
    nodes = space.nodes(program)
    inner = [n for n in nodes if n.parent >= 0]
    if not inner:
        return None
    donor = list(donors[int(rng.integers(len(donors)))])
    offered = space.nodes(donor)
    node = inner[int(rng.integers(len(inner)))]
    room = domain.tokens.max_len - (len(program) - (node.end - node.start))
    fitting = [m for m in offered if m.end - m.start <= room]
    if not fitting:
        return None
    expression = space.standalone(donor, fitting[int(rng.integers(len(fitting)))])
    return _fits(domain, space.splice(list(program), node, expression))


_GENERIC: dict[str, Callable] = {"jitter": jitter, "drop": drop, "graft": graft}


def edits_of(domain: Domain, names: Sequence[str] | None = None) -> dict[str, Edit]:
    """The edits of a domain by name, or those of ``names``: the generic ones, with the domain's own
    (:meth:`Domain.edits`) added or replacing them; a domain without a rewrite space and edits of its own has
    none."""
    out: dict[str, Edit] = {}
    if domain.rewrite is not None:
        out = {name: (lambda p, d, r, f=f: f(domain, p, d, r)) for name, f in _GENERIC.items()}
    out.update(domain.edits())
    if names is None:
        return out
    unknown = [n for n in names if n not in out]
    if unknown:
        raise KeyError(f"{domain.name} has no edit {', '.join(unknown)}; it offers {', '.join(out) or 'none'}")
    return {n: out[n] for n in names}


# ---- the stream -------------------------------------------------------------------------------------
def _draw(domain: Domain, programs: Sequence[Sequence[int]], rng: np.random.Generator, symmetry_share: float = 0.5,
          edit_share: float = 0.5, symmetries: Sequence[str] | None = None,
          edits: Sequence[str] | None = None) -> tuple[list[list[int]], list[list[int]]]:
    """(the transformed programs, each before its edit): :func:`transformed`'s draws."""
    syms = symmetries_of(domain, symmetries)
    moves = list(edits_of(domain, edits).values())
    donors = [[int(t) for t in p] for p in programs]
    out, before = [], []
    for program in donors:
        p = program
        if rng.random() < symmetry_share:
            k = int(rng.integers(len(syms) + 1))            # 0: the identity
            if k:
                p = _fits(domain, syms[k - 1].program(p)) or p
        q = p
        if moves and rng.random() < edit_share:
            q = _fits(domain, moves[int(rng.integers(len(moves)))](p, donors, rng)) or p
        out.append(q)
        before.append(p)
    return out, before


def transformed(domain: Domain, programs: Sequence[Sequence[int]], rng: np.random.Generator,
                symmetry_share: float = 0.5, edit_share: float = 0.5, symmetries: Sequence[str] | None = None,
                edits: Sequence[str] | None = None) -> list[list[int]]:
    """For each program: with probability ``symmetry_share`` one of the domain's symmetries or the identity
    (uniformly), then with probability ``edit_share`` one of its edits (uniformly; grafts draw their donor
    among ``programs``). A symmetry or edit that cannot apply leaves the program as it was, so every result
    is valid. ``symmetries``/``edits``: only those names (default: all the domain offers)."""
    return _draw(domain, programs, rng, symmetry_share, edit_share, symmetries, edits)[0]


def pairs(domain: Domain, programs: Sequence[Sequence[int]], rng: np.random.Generator,
          **same) -> tuple[np.ndarray, list[list[int]]]:
    """(shapes bool (N, *shape), programs): :func:`transformed` programs (keyword arguments ``same``) and
    their executions. Where a transformed program executes to an empty shape, the program before its edit
    replaces it, or where that is empty too the original (e.g. a difference that removes everything, a
    ShapeAssembly frame that became singular); every program executes exactly to its shape."""
    out, before = _draw(domain, programs, rng, **same)
    if not out:
        return np.zeros((0, *domain.shape), dtype=bool), []
    shapes = domain.execute(pad_programs(out)).cpu().numpy()
    for fallback in (before, [[int(t) for t in p] for p in programs]):
        empty = [i for i in range(len(out)) if out[i] != fallback[i] and not shapes[i].any()]
        if empty:
            shapes[empty] = domain.execute(pad_programs([fallback[i] for i in empty])).cpu().numpy()
            for i in empty:
                out[i] = fallback[i]
    return shapes, out


__all__ = ["GENERIC", "drop", "edits_of", "graft", "jitter", "pairs", "symmetries_of", "transformed", "valid"]
