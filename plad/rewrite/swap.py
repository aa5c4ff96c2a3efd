"""Swap: remove one primitive, insert the best new one where the residual says, keep it if that improves.

Insertion alone stops at the language's length cap (3D CSG: 12 primitives in
100 tokens), and on the PartNet test shapes nine tenths of the search's loss
is in programs at that cap: the primitives placed early, when the residual
was large, stay even where a better one would fit now. A swap frees a place
first: the program without each of its primitives (the domain's
:meth:`~plad.domains.space.RewriteSpace.removals`: for a tree, a leaf's
parent replaced by its sibling, as pruning removes a node), then the
domain's insertion candidates on each of those, all of them in one batch;
per program the best candidate (screened, scored exactly) is tuned by PO
over its new last block and kept only if the result beats the program
(metric, then fewer tokens). So a swap never makes a program worse, and
every kept value is exact.
"""
from __future__ import annotations

import time
from collections.abc import Sequence

import torch

from plad.rewrite.evaluate import Scorer
from plad.rewrite.insert import keep_tuned, take_best
from plad.rewrite.prune import removal_candidates


def swap(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, sweeps: int, wide: bool = False,
         only: Sequence[int] | None = None, deadline: float | None = None,
         ) -> tuple[list[list[int]], torch.Tensor, torch.Tensor]:
    """One swap step for each program (or those in ``only``); returns (programs, values, swapped (B,) bool).

    ``sweeps``: PO sweeps over the inserted primitive's block before the decision (a fitted box overshoots
    before tuning).
    """
    programs = [list(p) for p in programs]
    values = values.clone()
    rows = list(range(len(programs))) if only is None else list(only)
    shorter, owner = removal_candidates(scorer.space, programs, rows)
    if not shorter or (deadline is not None and time.perf_counter() > deadline):
        return programs, values, torch.zeros(len(programs), dtype=torch.bool)
    owner_t = torch.tensor(owner, dtype=torch.long)
    cands = scorer.space.insertions(shorter, scorer.outputs(shorter), scorer.targets[owner_t])
    if not len(cands):
        return programs, values, torch.zeros(len(programs), dtype=torch.bool)
    cands.owner = owner_t[cands.owner]                       # back to indices of ``programs``
    new, new_values, tried = take_best(scorer, programs, values, cands, force=True)
    programs, values, swapped = keep_tuned(scorer, programs, values, new, new_values, tried, sweeps, wide, deadline)
    scorer.stats.accepted("swap", int(swapped.sum()))
    return programs, values, swapped


__all__ = ["swap"]
