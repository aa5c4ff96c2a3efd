"""Swap: remove one primitive, insert the best new one where the residual says, keep it if that improves.

Insertion alone stops at the language's length cap (3D CSG: 12 primitives in
100 tokens), and on the PartNet test shapes nine tenths of the search's loss
is in programs at that cap: the primitives placed early, when the residual
was large, stay even where a better one would fit now. A swap frees a place
first: for every leaf of the program's expression tree (a primitive), the
program without it (its parent replaced by its sibling, as pruning removes
a node), then the domain's insertion candidates on each of those, all of
them in one batch; per program the best candidate (screened, scored
exactly) is tuned by PO over its new last block and kept only if the result
beats the program (metric, then fewer tokens). So a swap never makes a
program worse, and every kept value is exact.
"""
from __future__ import annotations

import time
from collections.abc import Sequence

import torch

from plad.rewrite.evaluate import Scorer, improves
from plad.rewrite.po import optimize


def removals(space, program: Sequence[int]) -> list[list[int]]:
    """The program without each of its primitives (leaves whose parent is an operator), in token order."""
    if not program:
        return []
    nodes = space.nodes(program)
    out = []
    for n, node in enumerate(nodes):
        if node.boolean or node.parent < 0:
            continue
        parent = nodes[node.parent]
        siblings = [c for c in parent.children if c != n]
        if len(siblings) == 1:
            out.append(space.splice(program, parent, space.standalone(program, nodes[siblings[0]])))
    return out


def swap(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, sweeps: int, wide: bool = False,
         only: Sequence[int] | None = None, deadline: float | None = None,
         ) -> tuple[list[list[int]], torch.Tensor, torch.Tensor]:
    """One swap step for each program (or those in ``only``); returns (programs, values, swapped (B,) bool).

    ``sweeps``: PO sweeps over the inserted primitive's block before the decision (a fitted box overshoots
    before tuning).
    """
    programs = [list(p) for p in programs]
    values = values.clone()
    swapped = torch.zeros(len(programs), dtype=torch.bool)
    rows = list(range(len(programs))) if only is None else list(only)
    space = scorer.space
    shorter, owner = [], []
    for i in rows:
        for p in removals(space, programs[i]):
            shorter.append(p)
            owner.append(i)
    if not shorter or (deadline is not None and time.perf_counter() > deadline):
        return programs, values, swapped
    owner_t = torch.tensor(owner, dtype=torch.long)
    outputs = scorer.outputs(shorter)
    cands = space.insertions(shorter, outputs, scorer.targets[owner_t])
    if not len(cands):
        return programs, values, swapped
    cands.owner = owner_t[cands.owner]                       # back to indices of ``programs``
    best, best_values = scorer.best(cands, len(programs))
    tried = [i for i in rows if int(best[i]) >= 0]
    if not tried:
        return programs, values, swapped
    new = [list(p) for p in programs]
    new_values = values.clone()
    for i in tried:
        new[i] = cands.row(int(best[i]))
        new_values[i] = best_values[i]
    if sweeps > 0:
        new, new_values = optimize(scorer, new, new_values, sweeps=sweeps, wide=wide, last_only=True, only=tried,
                                   deadline=deadline)
    lengths = torch.tensor([len(p) for p in programs])
    new_lengths = torch.tensor([len(p) for p in new])
    ok = torch.zeros(len(programs), dtype=torch.bool)
    ok[tried] = True
    ok &= improves(new_values, new_lengths, values, lengths, scorer.higher_is_better)
    for i in torch.nonzero(ok).flatten().tolist():
        programs[i] = new[i]
        values[i] = new_values[i]
    swapped[ok] = True
    scorer.stats.accepted("swap", int(ok.sum()))
    return programs, values, swapped


__all__ = ["removals", "swap"]
