"""The voxelizer's grid-aligned cuboids compiled with numba: the same booleans and unique counts.

:func:`plad.data.datasets.partnet.voxels.voxelize_batch` counts, per voxel of a shape, the cuboids covering it;
a grid-aligned cuboid covers the outer product of its three per-axis masks, which the tensor path sums as float32
matrix products (exact: integer sums far below 2^24). Here the same counts are integers added voxel by voxel,
only over each cuboid's own voxels, and a cuboid's unique voxels (covered once in its shape) are counted the same
way. The masks themselves are computed as before (numpy, float64), so the inputs are the same booleans.
"""
from __future__ import annotations

import numpy as np

from plad.jit import compiler

njit = compiler()   # None without numba: the caller keeps its tensor path

__all__ = ["aligned", "available", "rotated"]


def available() -> bool:
    """Whether the kernels can run here (numba importable)."""
    return njit is not None


if njit is not None:
    @njit(cache=True, nogil=True)
    def aligned(masks, slots, counts, out, unique_pass):
        """The grid-aligned cuboids: masks bool (M, 3, res), their per-axis masks; slots int64 (S, K), the masks'
        rows of each shape's cuboids (-1: none). Without unique_pass, counts int32 (S, res, res, res) += each
        cuboid's voxels; with it, out int64 (S, K) = how many of them its shape covers exactly once."""
        n_shapes, k_max = slots.shape
        res = masks.shape[2]
        for s in range(n_shapes):
            for k in range(k_max):
                j = slots[s, k]
                total = 0
                if j >= 0:
                    for x in range(res):
                        if not masks[j, 0, x]:
                            continue
                        for y in range(res):
                            if not masks[j, 1, y]:
                                continue
                            for z in range(res):
                                if masks[j, 2, z]:
                                    if unique_pass:
                                        total += counts[s, x, y, z] == 1
                                    else:
                                        counts[s, x, y, z] += 1
                if unique_pass:
                    out[s, k] = total

    @njit(cache=True, nogil=True)
    def rotated(p, u, half, lo, hi, centers, cubes, shape_of, counts, out, unique_pass):
        """The rotated cuboids ``cubes`` (indices; finite axes) over their boxes [lo, hi], with voxels.py's
        _rotated_box test (the same float64 operations in the same order): without unique_pass,
        counts[shape_of[i]] += each one's voxels; with it, out[i] = how many of them the shape covers once."""
        k = np.empty(3, dtype=np.int64)
        uu = np.empty((3, 3), dtype=np.float64)
        hh = np.empty(3, dtype=np.float64)
        for i in range(cubes.shape[0]):
            m = cubes[i]
            s = shape_of[i]
            nonzero = 0
            for a in range(3):
                hh[a] = half[m, a]
                best = -1.0
                for g in range(3):
                    uu[a, g] = u[m, a, g]
                    v = abs(u[m, a, g])
                    if u[m, a, g] != 0:
                        nonzero += 1
                    if v > best:                      # the first largest, as argmax
                        best = v
                        k[a] = g
            separable = nonzero == 3                  # the original's separable branch
            p0, p1, p2 = p[m, 0], p[m, 1], p[m, 2]
            total = 0
            for x in range(lo[m, 0], hi[m, 0] + 1):
                dx = centers[x] - p0
                for y in range(lo[m, 1], hi[m, 1] + 1):
                    dy = centers[y] - p1
                    for z in range(lo[m, 2], hi[m, 2] + 1):
                        dz = centers[z] - p2
                        inside = True
                        for a in range(3):
                            if separable:
                                g = k[a]
                                d = dx if g == 0 else (dy if g == 1 else dz)
                                ok = abs(d * uu[a, g]) <= hh[a]
                            else:
                                ok = abs(dx * uu[a, 0] + dy * uu[a, 1] + dz * uu[a, 2]) <= hh[a]
                            if not ok:
                                inside = False
                                break
                        if inside:
                            if unique_pass:
                                total += counts[s, x, y, z] == 1
                            else:
                                counts[s, x, y, z] += 1
            if unique_pass:
                out[i] = total
