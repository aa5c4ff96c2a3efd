"""Synthetic 2D CSG programs for supervised pretraining (CSGNet style).

A program has k primitives, k uniform in 1..7, combined by k-1 random
operators in a random valid postfix order. Draw tokens are uniform over the
vocabulary. Programs are executed in batches and rejected when degenerate:
the canvas is empty or full, or an operator's result equals one of its
operands (the operator did nothing useful, e.g. the union with a contained
shape or the difference of disjoint shapes).
"""
from __future__ import annotations

import numpy as np

from plad.domains.base import pad_programs
from plad.domains.csg2d.executor import Executor

MAX_PRIMITIVES = 7


def _structure(k: int, rng: np.random.Generator) -> list[bool]:
    """A random valid postfix layout of k draws and k-1 operators (True = draw)."""
    out: list[bool] = []
    depth, draws, ops = 0, k, k - 1
    while draws or ops:
        can_draw, can_op = draws > 0, depth >= 2 and ops > 0
        # weighting by what is left makes every layout reachable and keeps trees varied
        if can_draw and (not can_op or rng.random() < draws / (draws + ops)):
            out.append(True)
            draws -= 1
            depth += 1
        else:
            out.append(False)
            ops -= 1
            depth -= 1
    return out


def sample_programs(executor: Executor, n: int, rng: np.random.Generator,
                    min_primitives: int = 1, max_primitives: int = MAX_PRIMITIVES) -> list[list[int]]:
    """``n`` valid non-degenerate programs (token ids, ending with ``$``)."""
    table = executor.table
    draws = np.array([i for i, t in enumerate(table.tokens) if t.kind == "draw"])
    ops = np.array([i for i, t in enumerate(table.tokens) if t.kind in ("union", "intersection", "difference")])
    stop = table.index("$")
    # Equal numbers of programs per primitive count: short programs are rejected
    # far less often, so sampling k uniformly and filtering would skew lengths.
    counts = np.bincount(rng.integers(min_primitives, max_primitives + 1, size=n),
                         minlength=max_primitives + 1)
    kept: dict[int, list[list[int]]] = {k: [] for k in range(min_primitives, max_primitives + 1)}
    while True:
        wanted = {k: int(counts[k]) - len(kept[k]) for k in kept if counts[k] > len(kept[k])}
        if not wanted:
            break
        ks, progs = [], []
        for k, missing in wanted.items():
            for _ in range(max(32, 3 * missing)):
                ks.append(k)
                progs.append(_random_program(k, draws, ops, stop, rng))
        words, degenerate = executor.run_packed(pad_programs(progs, pad=stop), check_degenerate=True)
        empty = (words == 0).all(dim=1)
        full = (words == -1).all(dim=1)
        good = (~(degenerate | empty | full)).tolist()
        for k, prog, g in zip(ks, progs, good):
            if g and len(kept[k]) < counts[k]:
                kept[k].append(prog)
    out = [p for k in kept for p in kept[k]]
    order = rng.permutation(len(out))
    return [out[i] for i in order]


def _random_program(k: int, draws: np.ndarray, ops: np.ndarray, stop: int,
                    rng: np.random.Generator) -> list[int]:
    d = iter(rng.choice(draws, size=k).tolist())
    o = iter(rng.choice(ops, size=k - 1).tolist())
    return [next(d) if is_draw else next(o) for is_draw in _structure(k, rng)] + [stop]
