"""Synthetic 3D CSG programs for supervised pretraining (paper supplement; docs/domains.md).

1. K primitives, K uniform in 2..12, each a cuboid or an ellipsoid (50/50).
   Per axis, the center is a rounded normal (mean 16, sd 16/3) resampled
   until it lies in [2, 30]; the full extent a rounded normal (mean 0.75 m,
   sd m/2) resampled until it lies in [2, 2m - 2], with m = min(c, 32 - c),
   so that the primitive stays inside the grid.
2. Bounding-box overlaps between the primitives (boxes ``c +- d/2``; two
   boxes overlap when they share positive volume).
3. A binary operator tree: repeatedly pick an ordered pair of groups (A, B)
   at random and merge them with an operator drawn uniformly among the valid
   ones: union always; difference ``A - B`` if every primitive of B overlaps
   some primitive of A; intersection if, in addition, every primitive of A
   overlaps some primitive of B. The tree is written out in prefix order.
4. All candidates are executed in batches and a program is rejected when
   some operator's result is empty or equal to one of its operands.

Quotas per K keep the accepted programs uniform over K (programs with more
primitives are rejected more often, so filtering a uniform K would skew it;
:mod:`plad.domains.synthetic`); each batch proposes per K about what the
last batch's acceptance rate of K says is needed.
"""
from __future__ import annotations

import numpy as np

from plad.domains.base import pad_programs
from plad.domains.csg3d.executor import Executor
from plad.domains.csg3d.tokens import OPERATORS, PRIMITIVES, RES
from plad.domains.synthetic import stratified_rejection_sample

MIN_PRIMITIVES, MAX_PRIMITIVES = 2, 12
CENTER_MEAN, CENTER_SD, CENTER_LO, CENTER_HI = RES / 2, RES / 6, 2, RES - 2


def _rounded_normal(rng: np.random.Generator, mean, sd, lo, hi) -> np.ndarray:
    """Elementwise rounded normals (arrays of equal shape), each resampled until in [lo, hi]."""
    mean, sd, lo, hi = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (mean, sd, lo, hi)))
    out = np.rint(rng.normal(mean, sd))
    bad = (out < lo) | (out > hi)
    while bad.any():
        out[bad] = np.rint(rng.normal(mean[bad], sd[bad]))
        bad = (out < lo) | (out > hi)
    return out.astype(np.int64)


def sample_primitives(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` primitives: params (n, 6) int64 ``x y z dx dy dz`` and ellipsoid (n,) bool."""
    c = _rounded_normal(rng, np.full((n, 3), CENTER_MEAN), CENTER_SD, CENTER_LO, CENTER_HI)
    m = np.minimum(c, RES - c).astype(np.float64)                         # room to the nearer border
    d = _rounded_normal(rng, 0.75 * m, m / 2, 2, 2 * m - 2)
    return np.concatenate([c, d], axis=1), rng.random(n) < 0.5


def overlaps(params: np.ndarray) -> np.ndarray:
    """(k, k) bool: the bounding boxes ``c +- d/2`` of two primitives share positive volume."""
    c, d = params[:, :3], params[:, 3:]
    return (2 * np.abs(c[:, None] - c[None]) < d[:, None] + d[None]).all(-1)


def random_tree(params: np.ndarray, ellipsoid: np.ndarray, rng: np.random.Generator) -> list[str]:
    """Merge the primitives into one overlap-aware operator tree; returns its prefix token names."""
    k = len(params)
    ov = overlaps(params)
    groups = [[i] for i in range(k)]                                      # primitive indices per group
    texts = [[PRIMITIVES[int(e)], *map(str, p.tolist())] for p, e in zip(params, ellipsoid)]
    u = rng.random((k - 1, 3))                                            # all random draws of the merges
    for step in range(k - 1):
        g = len(groups)
        i = int(u[step, 0] * g)
        j = int(u[step, 1] * (g - 1))
        j += j >= i                                                       # an ordered pair i != j
        A, B = groups[i], groups[j]
        b_in_a = ov[np.ix_(B, A)].any(1).all()                            # every prim of B meets A
        a_in_b = ov[np.ix_(A, B)].any(1).all()
        valid = ["union"] + (["diff"] if b_in_a else []) + (["inter"] if b_in_a and a_in_b else [])
        op = valid[int(u[step, 2] * len(valid))]
        merged_text = [op, *texts[i], *texts[j]]
        for drop in sorted((i, j), reverse=True):
            del groups[drop], texts[drop]
        groups.append(A + B)
        texts.append(merged_text)
    return texts[0]


def candidates(ks: list[int], rng: np.random.Generator) -> list[list[str]]:
    """Unfiltered programs with ks[i] primitives each, as token names.

    The primitives of all programs are drawn at once (numpy per call overhead
    dominates otherwise); only the tree building is per program.
    """
    params, ell = sample_primitives(int(sum(ks)), rng)
    ends = np.cumsum(ks)
    return [random_tree(params[e - k:e], ell[e - k:e], rng) for k, e in zip(ks, ends)]


def sample_programs(executor: Executor, n: int, rng: np.random.Generator,
                    min_primitives: int = MIN_PRIMITIVES, max_primitives: int = MAX_PRIMITIVES,
                    batch: int = 2048) -> list[list[int]]:
    """``n`` valid non-degenerate programs (token ids), uniform over the number of primitives."""
    table = executor.table
    assert set(OPERATORS) <= set(table.names)

    def propose(wanted: dict[int, int], rates: dict[int, float],
                rng: np.random.Generator) -> tuple[list[int], list[list[int]]]:
        ks: list[int] = []
        for k, missing in wanted.items():
            # enough candidates for the expected rejections, a few more for luck
            ks += [k] * min(batch, int(missing / max(rates[k], 0.05) * 1.2) + 8)
        return ks, [table.encode(names) for names in candidates(ks, rng)]

    def accept(progs: list[list[int]]) -> list[bool]:
        _, degenerate = executor.run_packed(pad_programs(progs), check_degenerate=True)
        return (~degenerate).tolist()

    return stratified_rejection_sample(n, rng, range(min_primitives, max_primitives + 1), propose, accept,
                                       initial_rate=0.5)
