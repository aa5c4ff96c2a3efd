"""Canonical 3D CSG programs and the one-box floor.

Canonical form (docs/domains.md, "Canonical programs"): a program with exactly the
same execution in which every free choice the execution cannot show is fixed:

* **cuboids**: a cuboid is the product of one voxel interval per axis,
  ``[c - floor(d/2), c + floor(d/2)]`` clipped to the grid (the inside test
  ``2|p - c| <= d`` on integer voxel centres), so extents ``2k`` and ``2k + 1``
  give the same voxels, and near a border centres and extents that clip to
  the same interval do too. Each (centre, extent) pair of an axis is replaced
  by the representative of its interval: the smallest half extent
  ``floor(d/2)``, then an odd extent, then the smallest centre;
* **ellipsoids**: the voxels an ellipsoid covers relative to its centre depend
  only on its extents, and different extent triples often cover the same
  lattice points. Every triple is replaced by the member of its class with
  the smallest sum, then the lexicographically smallest (the classes are
  found by rendering all 31^3 triples once, unclipped, at the grid centre);
  the centre is kept, so clipping is the same;
* **union / inter** operands are ordered by their (canonical) token
  sequences, smaller first; ``diff`` keeps its order.

Rewriting neither adds nor removes tokens. The one-box floor is the cuboid
whose voxels are the tightest axis-aligned box around a target (or, where
that interval has no cuboid, the best of its nearest intervals by IoU).
"""
from __future__ import annotations

import itertools
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import torch

from plad.domains.csg3d.executor import render_primitives, unpack
from plad.domains.csg3d.tokens import PARAM_MAX, PARAM_MIN, PRIMITIVES, RES, program_tree, token_table
from plad.metrics import iou

_VALUES = np.arange(PARAM_MIN, PARAM_MAX + 1)


def axis_interval(c: int, d: int) -> tuple[int, int]:
    """The voxel interval [lo, hi] (clipped to the grid) a cuboid covers along one axis."""
    return max(c - d // 2, 0), min(c + d // 2, RES - 1)


@lru_cache(maxsize=1)
def cuboid_axis_table() -> dict[tuple[int, int], tuple[int, int]]:
    """(centre, extent) -> the representative (centre, extent) of the same clipped interval."""
    classes: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for c in _VALUES:
        for d in _VALUES:
            classes.setdefault(axis_interval(int(c), int(d)), []).append((int(c), int(d)))
    out = {}
    for members in classes.values():
        rep = min(members, key=lambda cd: (cd[1] // 2, cd[1] % 2 == 0, cd[0]))
        out.update({m: rep for m in members})
    return out


@lru_cache(maxsize=1)
def interval_cuboids() -> dict[tuple[int, int], tuple[int, int]]:
    """Clipped interval [lo, hi] -> its representative (centre, extent), for every interval a cuboid can cover."""
    return {axis_interval(*cd): rep for cd, rep in cuboid_axis_table().items()}


@lru_cache(maxsize=1)
def ellipsoid_extent_table() -> np.ndarray:
    """(32, 32, 32, 3) int: [dx, dy, dz] -> the representative extents of the ellipsoids covering the same voxels
    around their centre (indices 1..31 used)."""
    d = np.array(list(itertools.product(_VALUES, repeat=3)), dtype=np.int64)            # (31^3, 3)
    centre = np.full_like(d, RES // 2)     # offsets up to 15 stay inside the grid: no clipping
    words = []
    for start in range(0, len(d), 4096):   # (chunk, 1024) int32 packed grids
        params = torch.from_numpy(np.concatenate([centre[start:start + 4096], d[start:start + 4096]], 1))
        words.append(render_primitives(params, torch.ones(len(params), dtype=torch.bool)).reshape(len(params), -1))
    grids = torch.cat(words).numpy()
    ids: dict[bytes, int] = {}        # class id of each distinct grid, in order of appearance
    cls = np.array([ids.setdefault(row.tobytes(), len(ids)) for row in grids])
    # representative: smallest sum, then lexicographically smallest (d is already in lexicographic order)
    order = np.lexsort((np.arange(len(d)), d.sum(1), cls))
    first = np.zeros(cls.max() + 1, dtype=np.int64)
    seen = np.zeros(cls.max() + 1, dtype=bool)
    for i in order:               # the first member of each class in (class, sum, lexicographic) order
        if not seen[cls[i]]:
            seen[cls[i]] = True
            first[cls[i]] = i
    table = np.zeros((RES, RES, RES, 3), dtype=np.int64)
    table[d[:, 0], d[:, 1], d[:, 2]] = d[first[cls]]
    return table


def _canonical_primitive(name: str, params: tuple[int, ...]) -> tuple[int, ...]:
    c, d = params[:3], params[3:]
    if name == "cuboid":
        table = cuboid_axis_table()
        reps = [table[(c[a], d[a])] for a in range(3)]
        return tuple(r[0] for r in reps) + tuple(r[1] for r in reps)
    return tuple(c) + tuple(int(v) for v in ellipsoid_extent_table()[d[0], d[1], d[2]])


def canonical_program(ids: Sequence[int]) -> list[int]:
    """The canonical form of a valid csg3d program (token ids); see the module docstring."""
    table = token_table()

    def emit(node) -> list[int]:
        name = node[0]
        if name in PRIMITIVES:
            params = _canonical_primitive(name, node[1])
            return [table.index(name)] + [table.index(str(v)) for v in params]
        a, b = emit(node[1]), emit(node[2])
        if name in ("union", "inter") and b < a:
            a, b = b, a
        return [table.index(name)] + a + b

    return emit(program_tree(ids))


def _axis_candidates(lo: int, hi: int) -> list[tuple[int, int]]:
    """(centre, extent) of the cuboid intervals nearest to [lo, hi]: the interval itself when a cuboid covers it,
    else those one voxel wider or narrower at either end."""
    known = interval_cuboids()
    if (lo, hi) in known:
        return [known[(lo, hi)]]
    near = {(lo + a, hi + b) for a in (-1, 0, 1) for b in (-1, 0, 1)}
    return [known[iv] for iv in sorted(near) if iv in known]


def one_box(targets: np.ndarray) -> list[list[int]]:
    """The one-box floor: per target (bool (N, 32, 32, 32)), the cuboid program with the best IoU among those
    covering the tightest axis-aligned box around it (or the nearest boxes a cuboid can cover)."""
    table = token_table()
    out = []
    for target in targets:
        if not target.any():   # nothing to cover: the smallest cuboid (every program scores 0)
            out.append([table.index("cuboid")] + [table.index(str(v)) for v in (16, 16, 16, 1, 1, 1)])
            continue
        axes = []
        for a in range(3):
            occupied = np.nonzero(target.any(axis=tuple(b for b in range(3) if b != a)))[0]
            axes.append(_axis_candidates(int(occupied[0]), int(occupied[-1])))
        combos = list(itertools.product(*axes))
        params = torch.tensor([[cd[0] for cd in combo] + [cd[1] for cd in combo] for combo in combos])
        grids = unpack(render_primitives(params, torch.zeros(len(params), dtype=torch.bool)))
        values = iou(grids, torch.from_numpy(target)[None].expand_as(grids))
        best = params[int(values.argmax())].tolist()
        out.append([table.index("cuboid")] + [table.index(str(v)) for v in best])
    return out
