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


def random_tree(params: np.ndarray, ellipsoid: np.ndarray, rng: np.random.Generator,
                op_weights: dict[str, float] | None = None) -> list[str]:
    """Merge the primitives into one overlap-aware operator tree; returns its prefix token names.

    ``op_weights`` (default: equal) weighs the valid operators of a merge (union is always valid).
    """
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
        if op_weights is None:
            op = valid[int(u[step, 2] * len(valid))]
        else:
            w = np.cumsum([op_weights.get(v, 0.0) for v in valid])
            op = valid[min(int(np.searchsorted(w, u[step, 2] * w[-1], side="right")), len(valid) - 1)]
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


# -- the "parts" sampler (beyond the paper) --------------------------------------------------------------
#: operator weights of the parts sampler's merges: assemblies of parts, a few cut-outs, no intersections
PARTS_OPS = {"union": 0.85, "diff": 0.15, "inter": 0.0}
#: part kinds and their shares: a plate (one thin axis), a stick (two thin axes), a block (none)
PART_KINDS = (("plate", 0.4), ("stick", 0.35), ("block", 0.25))
MIRROR_SHARE, ELLIPSOID_SHARE, FACE_SHARE, CENTRED_SHARE = 0.9, 0.1, 0.5, 0.4


def _odd_interval(rng: np.random.Generator, lo: int, hi: int, length: int) -> tuple[int, int]:
    """A voxel interval of ``length`` (made odd, at most the room) inside [lo, hi]; half the time
    against one end of it (a part resting on the floor, a back against the rear)."""
    room = hi - lo + 1
    length = max(1, min(length, room))
    if length % 2 == 0:
        length -= 1
    r = rng.random()
    if r < FACE_SHARE / 2:
        start = lo
    elif r < FACE_SHARE:
        start = hi - length + 1
    else:
        start = int(rng.integers(lo, hi - length + 2))
    return start, start + length - 1


def _interval_params(a: int, b: int) -> tuple[int, int]:
    """(centre, extent) of the odd voxel interval [a, b] (centres are at least 1: index 0 is reached
    from centre 1 with extent 3)."""
    if a == b == 0:
        a, b = 0, 2
    c, d = (a + b) // 2, b - a + 1
    return max(c, 1), d


def sample_parts(k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``k`` cuboid-like parts of one object: params (k, 6) int64 and ellipsoid (k,) bool.

    The object's box spans the full height (y) most of the time and is centred in x and z, as the
    voxelized PartNet shapes are; parts are plates, sticks and blocks inside it, half of their
    intervals against a face of the box, some centred in x, and a part wholly on one side of the x
    centre mostly gets a mirror twin (x -> 31 - x), as furniture is mostly symmetric left to right
    (the voxelized PartNet training shapes: IoU 0.94 with their own x mirror).
    """
    height = RES if rng.random() < 0.7 else int(rng.integers(12, RES + 1))
    box = []
    for axis in range(3):
        ext = height if axis == 1 else int(rng.integers(10, RES + 1))
        lo = 0 if axis == 1 else (RES - ext) // 2
        box.append((lo, lo + ext - 1))
    params, ell = [], []
    while len(params) < k:
        kind = PART_KINDS[int(np.searchsorted(np.cumsum([w for _, w in PART_KINDS]), rng.random()))][0]
        thin = {"plate": 1, "stick": 2, "block": 0}[kind]
        thin_axes = set(rng.choice(3, size=thin, replace=False).tolist())
        p = []
        for axis in range(3):
            lo, hi = box[axis]
            room = hi - lo + 1
            if axis in thin_axes:
                length = int(rng.choice([1, 3], p=[0.6, 0.4]))
            elif kind == "block":
                length = int(rng.integers(max(1, room // 5), room + 1))
            else:
                length = int(rng.integers(max(1, int(room * 0.3)), room + 1))
            if axis == 0 and thin_axes != {0} and rng.random() < CENTRED_SHARE:   # a seat, a top: centred in x
                half = (min(length, hi - lo + 1) - 1) // 2
                p.append(((RES - 1) // 2 - half, (RES - 1) // 2 + half))
            else:
                p.append(_odd_interval(rng, lo, hi, length))
        xa, xb = p[0]
        if xa < RES // 2 <= xb and rng.random() < MIRROR_SHARE:   # across the x centre: made symmetric
            half = (xb - xa) // 2
            p[0] = ((RES - 1) // 2 - half, (RES - 1) // 2 + half)
        e = rng.random() < ELLIPSOID_SHARE
        (cx, dx), (cy, dy), (cz, dz) = (_interval_params(*i) for i in p)
        params.append((cx, cy, cz, dx, dy, dz))
        ell.append(e)
        (xa, xb) = p[0]
        if len(params) < k and xb < RES - 1 - xb and rng.random() < MIRROR_SHARE:   # wholly left of the centre
            mx, mdx = _interval_params(RES - 1 - xb, RES - 1 - xa)
            params.append((mx, cy, cz, mdx, dy, dz))
            ell.append(e)
    return np.array(params, dtype=np.int64), np.array(ell, dtype=bool)


def sample_parts_programs(executor: Executor, n: int, rng: np.random.Generator,
                          min_primitives: int = MIN_PRIMITIVES, max_primitives: int = MAX_PRIMITIVES,
                          batch: int = 2048) -> list[list[int]]:
    """``n`` valid non-degenerate programs of the parts sampler (:func:`sample_parts`, merged mostly by
    union, :data:`PARTS_OPS`), uniform over the number of primitives, filtered as :func:`sample_programs`."""
    table = executor.table

    def propose(wanted: dict[int, int], rates: dict[int, float],
                rng: np.random.Generator) -> tuple[list[int], list[list[int]]]:
        ks: list[int] = []
        for k, missing in wanted.items():
            ks += [k] * min(batch, int(missing / max(rates[k], 0.05) * 1.2) + 8)
        progs = []
        for k in ks:
            params, ell = sample_parts(k, rng)
            progs.append(table.encode(random_tree(params, ell, rng, PARTS_OPS)))
        return ks, progs

    def accept(progs: list[list[int]]) -> list[bool]:
        _, degenerate = executor.run_packed(pad_programs(progs), check_degenerate=True)
        return (~degenerate).tolist()

    return stratified_rejection_sample(n, rng, range(min_primitives, max_primitives + 1), propose, accept,
                                       initial_rate=0.5)
