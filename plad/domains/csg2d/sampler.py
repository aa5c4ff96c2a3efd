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
from plad.domains.synthetic import stratified_rejection_sample

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
    """``n`` valid non-degenerate programs (token ids, ending with ``$``), uniform over the primitive count."""
    table = executor.table
    draws = np.array([i for i, t in enumerate(table.tokens) if t.kind == "draw"])
    ops = np.array([i for i, t in enumerate(table.tokens) if t.kind in ("union", "intersection", "difference")])
    stop = table.index("$")

    def propose(wanted: dict[int, int], rates, rng: np.random.Generator) -> tuple[list[int], list[list[int]]]:
        ks, progs = [], []
        for k, missing in wanted.items():
            for _ in range(max(32, 3 * missing)):
                ks.append(k)
                progs.append(_random_program(k, draws, ops, stop, rng))
        return ks, progs

    def accept(progs: list[list[int]]) -> list[bool]:
        words, degenerate = executor.run_packed(pad_programs(progs, pad=stop), check_degenerate=True)
        empty = (words == 0).all(dim=1)
        full = (words == -1).all(dim=1)
        return (~(degenerate | empty | full)).tolist()

    return stratified_rejection_sample(n, rng, range(min_primitives, max_primitives + 1), propose, accept)


def _random_program(k: int, draws: np.ndarray, ops: np.ndarray, stop: int,
                    rng: np.random.Generator) -> list[int]:
    d = iter(rng.choice(draws, size=k).tolist())
    o = iter(rng.choice(ops, size=k - 1).tolist())
    return [next(d) if is_draw else next(o) for is_draw in _structure(k, rng)] + [stop]
