"""Parameter optimization (PO): discrete coordinate descent over the domain's declared slots.

The program's structure stays fixed; its substitutable tokens (a primitive's
parameters, a draw token, an operator: whatever the domain's
:meth:`~plad.domains.space.RewriteSpace.blocks` declares) change one at a
time. A sweep visits the blocks in token order; at block j every program
that has one tries every single-slot substitution of its block j, all
programs' candidates in one batch, and keeps the best if it improves the
objective (metric, then fewer tokens). Sweeps repeat until a sweep changes
nothing (a coordinate-wise local optimum) or the budget ends. This is the
discrete counterpart of SIRI's PO, whose languages are discretized anyway
(../shared/specs/rewriting.md).
"""
from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from plad.domains.space import Candidates, Slot
from plad.rewrite.evaluate import Scorer, improves


def _block_candidates(programs: Sequence[Sequence[int]], rows: Sequence[int],
                      blocks: Sequence[Sequence[Slot]]) -> Candidates:
    """Every single-slot substitution of ``blocks[k]`` in ``programs[rows[k]]``, as one batch."""
    owner, position, token, base = [], [], [], []
    for k, (i, block) in enumerate(zip(rows, blocks)):
        for slot in block:
            n = len(slot.choices)
            owner.append(np.full(n, i, dtype=np.int64))
            base.append(np.full(n, k, dtype=np.int64))
            position.append(np.full(n, slot.position, dtype=np.int64))
            token.append(np.asarray(slot.choices, dtype=np.int64))
    if not owner:
        return Candidates.from_lists([], [])
    lengths = np.array([len(programs[i]) for i in rows], dtype=np.int64)
    padded = np.zeros((len(rows), int(lengths.max())), dtype=np.int64)
    for k, i in enumerate(rows):
        padded[k, : lengths[k]] = programs[i]
    base_idx = np.concatenate(base)
    positions = np.concatenate(position)
    tokens = padded[base_idx]
    tokens[np.arange(len(tokens)), positions] = np.concatenate(token)
    return Candidates(torch.from_numpy(tokens), torch.from_numpy(lengths[base_idx]),
                      torch.from_numpy(np.concatenate(owner)), bases=torch.from_numpy(padded),
                      base=torch.from_numpy(base_idx), position=torch.from_numpy(positions))


def optimize(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, *, sweeps: int,
             wide: bool, last_only: bool = False, only: Sequence[int] | None = None,
             deadline: float | None = None) -> tuple[list[list[int]], torch.Tensor]:
    """Coordinate descent on each program (or those in ``only``); returns (programs, values), never worse.

    Program i is scored against the scorer's target i. ``values`` are the
    programs' exact values. ``sweeps``: at most this many
    passes over the blocks; ``wide``: the domain's large choice sets;
    ``last_only``: only each program's last block (where insertion appends
    its primitive); ``deadline``: ``time.perf_counter()`` value after which
    no new block is started.
    """
    space = scorer.space
    programs = [list(p) for p in programs]
    values = values.clone()
    active = [i for i in (range(len(programs)) if only is None else only) if len(programs[i])]
    accepted = 0
    for _ in range(sweeps):
        if not active or (deadline is not None and time.perf_counter() > deadline):
            break
        blocks = {i: space.blocks(programs[i], wide) for i in active}
        if last_only:
            blocks = {i: b[-1:] for i, b in blocks.items()}
        changed: set[int] = set()
        for j in range(max(len(b) for b in blocks.values())):
            if deadline is not None and time.perf_counter() > deadline:
                break
            rows = [i for i in active if len(blocks[i]) > j]
            cands = _block_candidates(programs, rows, [blocks[i][j] for i in rows])
            if not len(cands):
                continue
            best, best_values = scorer.best(cands, len(programs))
            lengths = torch.tensor([len(p) for p in programs])
            has = best >= 0
            new_len = torch.where(has, cands.lengths[best.clamp(min=0)], lengths)
            ok = has & improves(best_values, new_len, values, lengths, scorer.higher_is_better)
            for i in torch.nonzero(ok).flatten().tolist():
                programs[i] = cands.row(int(best[i]))
                values[i] = best_values[i]
                changed.add(i)
                accepted += 1
                b = space.blocks(programs[i], wide)
                blocks[i] = b[-1:] if last_only else b
        active = [i for i in active if i in changed]
    scorer.stats.accepted("po", accepted)
    return programs, values
