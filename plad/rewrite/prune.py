"""Code pruning (CP): SIRI's two pruning rules, executed exactly.

Over the expression tree the domain declares
(:meth:`~plad.domains.space.RewriteSpace.nodes`):

* **bottom-up**: execute every sub-expression (all nodes of all programs in
  one batch); a boolean node whose output equals one of its children's
  outputs is replaced by that child, and a node whose output is empty is
  removed (its parent replaced by its sibling). Repeated until nothing
  applies.
* **top-down**: score every proper sub-tree (primitives included) against
  the target; among those within a tolerance of the best one (SIRI: 0.001
  absolute or 0.005 relative), the shortest becomes the new program.

**Removal** (:func:`remove`, also for a domain without such a tree, e.g.
ShapeAssembly's parts): every program with one primitive fewer (the domain's
:meth:`~plad.domains.space.RewriteSpace.removals`) is scored, and the best
kept where it improves (ties win: it is shorter), until none does.
**Elimination** (:func:`eliminate`) takes the best removal whether or not it
improves, to bring a program grown past the length cap back within it.

Every other rewrite is checked by executing and scoring the whole new program and
kept only if it improves the objective (metric, then fewer tokens), so a
pruned program is never worse; a bottom-up splice leaves the execution
unchanged and only shortens the program.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from plad.domains.space import Candidates, Node
from plad.rewrite.evaluate import Scorer, improves, oriented
from plad.rewrite.insert import improve_repeatedly, take_best
from plad.rewrite.po import optimize

#: SIRI's tolerances of the top-down rule (absolute, relative to the best sub-tree's value)
TOLERANCE = (0.001, 0.005)


def _accept(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, proposals: dict[int, list[int]],
            ) -> int:
    """Score proposals {program index: new program} exactly; keep the improving ones. Returns how many."""
    if not proposals:
        return 0
    rows = list(proposals)
    new = scorer.values([proposals[i] for i in rows], rows)
    ok = improves(new, torch.tensor([len(proposals[i]) for i in rows]), values[rows],
                  torch.tensor([len(programs[i]) for i in rows]), scorer.higher_is_better)
    for k in torch.nonzero(ok).flatten().tolist():
        programs[rows[k]] = proposals[rows[k]]
        values[rows[k]] = new[k]
    return int(ok.sum())


def _bottom_up_splice(space, program: Sequence[int], nodes: list[Node], outputs: torch.Tensor) -> list[int] | None:
    """The first applicable bottom-up splice (children before parents), or None."""
    flat = outputs.reshape(len(nodes), -1)
    empty = ~flat.any(dim=1)
    for n, node in enumerate(nodes):
        if node.boolean:
            for c in node.children:
                if torch.equal(flat[n], flat[c]):
                    return space.splice(program, node, space.standalone(program, nodes[c]))
        if bool(empty[n]):
            shorter = space.without(program, nodes, n)
            if shorter is not None:
                return shorter
    return None


def bottom_up(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, max_rounds: int = 32) -> int:
    """Apply the bottom-up rule in place until nothing applies; returns the number of splices kept."""
    space = scorer.space
    kept = 0
    todo = [i for i, p in enumerate(programs) if p]
    for _ in range(max_rounds):
        trees = {i: space.nodes(programs[i]) for i in todo}
        trees = {i: t for i, t in trees.items() if any(n.boolean for n in t)}
        if not trees:
            break
        subprograms, spans = [], {}
        for i, nodes in trees.items():
            spans[i] = (len(subprograms), len(subprograms) + len(nodes))
            subprograms += [space.standalone(programs[i], n) for n in nodes]
        outputs = scorer.outputs(subprograms)
        proposals = {}
        for i, nodes in trees.items():
            a, b = spans[i]
            new = _bottom_up_splice(space, programs[i], nodes, outputs[a:b])
            if new is not None:
                proposals[i] = new
        n = _accept(scorer, programs, values, proposals)
        kept += n
        if n == 0:
            break
        todo = list(proposals)
    return kept


def top_down(scorer: Scorer, programs: list[list[int]], values: torch.Tensor,
             tolerance: tuple[float, float] = TOLERANCE) -> int:
    """Apply the top-down rule in place once; returns the number of programs replaced by a sub-tree."""
    space = scorer.space
    subprograms, owner = [], []
    for i, p in enumerate(programs):
        if p:
            for node in space.nodes(p):
                if node.parent >= 0:
                    subprograms.append(space.standalone(p, node))
                    owner.append(i)
    if not subprograms:
        return 0
    cands = Candidates.from_lists(subprograms, owner)
    sub_values = scorer.exact(cands.tokens, cands.owner)
    o = oriented(sub_values, scorer.higher_is_better).numpy()
    owner_np = np.asarray(owner)
    lengths = cands.lengths.numpy()
    proposals = {}
    for i in np.unique(owner_np):
        rows = np.nonzero(owner_np == i)[0]
        best = o[rows].min()
        close = rows[o[rows] <= best + max(tolerance[0], tolerance[1] * abs(best))]
        # the shortest sub-tree within the tolerance (SIRI); if it does not improve the
        # program, the best sub-tree may still do (ties: fewer tokens)
        shortest = close[np.lexsort((o[close], lengths[close]))[0]]
        best_row = rows[np.lexsort((lengths[rows], o[rows]))[0]]
        for r in (shortest, best_row):
            if bool(improves(sub_values[r:r + 1], cands.lengths[r:r + 1], values[i:i + 1],
                             torch.tensor([len(programs[i])]), scorer.higher_is_better)):
                proposals[int(i)] = subprograms[r]
                break
    # the sub-trees' values are exact already; _accept re-executes them to confirm
    return _accept(scorer, programs, values, proposals)


def removal_candidates(space, programs: Sequence[Sequence[int]], rows: Sequence[int],
                       ) -> tuple[list[list[int]], list[int]]:
    """(programs with one primitive fewer, the index in ``programs`` each comes from), over ``rows``."""
    shorter, owner = [], []
    for i in rows:
        for p in space.removals(programs[i]):
            shorter.append(p)
            owner.append(i)
    return shorter, owner


def remove(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, max_rounds: int = 32,
           ) -> tuple[list[list[int]], torch.Tensor]:
    """Removal of one primitive at a time (the domain's :meth:`removals`), each program's best removal kept
    where it improves (metric, then fewer tokens), repeated until none does; returns (programs, values),
    never worse."""
    return improve_repeatedly(scorer, programs, values,
                              lambda current, rows: removal_candidates(scorer.space, current, rows), max_rounds,
                              "remove")


def eliminate(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, max_len: int, sweeps: int = 3,
              ) -> tuple[list[list[int]], torch.Tensor]:
    """Backward elimination: each program longer than ``max_len`` tokens loses the primitive whose removal
    costs least (the domain's :meth:`removals`), is tuned by ``sweeps`` local PO sweeps, and so on until it
    fits. Unlike the other rewriters it may make a program worse: it shortens programs grown past the length
    cap (``SearchConfig.overshoot``), whose caller keeps a result only where it beats its own."""
    programs = [list(p) for p in programs]
    values = values.clone()
    while True:
        rows = [i for i, p in enumerate(programs) if len(p) > max_len]
        if not rows:
            return programs, values
        shorter, owner = removal_candidates(scorer.space, programs, rows)
        if not shorter:
            raise ValueError(f"elimination: program {rows[0]} is longer than {max_len} tokens and has no removal")
        programs, values, _ = take_best(scorer, programs, values, Candidates.from_lists(shorter, owner), force=True)
        if sweeps > 0:
            programs, values = optimize(scorer, programs, values, sweeps=sweeps, wide=False, only=rows)


def prune(scorer: Scorer, programs: list[list[int]], values: torch.Tensor,
          tolerance: tuple[float, float] = TOLERANCE) -> tuple[list[list[int]], torch.Tensor]:
    """Both rules (bottom-up, then top-down); returns (programs, values), never worse."""
    programs = [list(p) for p in programs]
    values = values.clone()
    n = bottom_up(scorer, programs, values)
    n += top_down(scorer, programs, values, tolerance)
    scorer.stats.accepted("prune", n)
    return programs, values
