"""Frozen copy of plad/domains/boxes.py before its summed-volume table went int32 and its box growing was written
out face by face (commit ffb0dca): the reference the fast one must equal box for box."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage


def prefix_sums(mask: np.ndarray) -> np.ndarray:
    """Summed-volume table of a 3D mask: entry [i, j, k] counts mask[:i, :j, :k] (shape + 1 per axis)."""
    out = np.zeros(tuple(n + 1 for n in mask.shape), dtype=np.int64)
    out[1:, 1:, 1:] = mask.cumsum(0).cumsum(1).cumsum(2)
    return out


def box_sum(sums: np.ndarray, lo: Sequence[int], hi: Sequence[int]) -> int:
    """Mask voxels in the box lo..hi (inclusive) from the summed-volume table."""
    (a0, a1, a2), (b0, b1, b2) = lo, (hi[0] + 1, hi[1] + 1, hi[2] + 1)
    return int(sums[b0, b1, b2] - sums[a0, b1, b2] - sums[b0, a1, b2] - sums[b0, b1, a2]
               + sums[a0, a1, b2] + sums[a0, b1, a2] + sums[b0, a1, a2] - sums[a0, a1, a2])


def grow_box(sums: np.ndarray, seed: Sequence[int]) -> tuple[list[int], list[int]]:
    """Grow a box from ``seed`` one face at a time while the new slab lies entirely in the mask.

    ``sums``: the mask's summed-volume table. At each step the face whose slab
    adds the most voxels grows. Returns (lo, hi), inclusive voxel bounds.
    """
    size = [n - 1 for n in sums.shape]
    lo, hi = [int(v) for v in seed], [int(v) for v in seed]
    while True:
        best, best_gain = None, 0
        for axis in range(3):
            for side in (-1, 1):
                a, b = list(lo), list(hi)
                if side < 0:
                    if lo[axis] == 0:
                        continue
                    a[axis] = b[axis] = lo[axis] - 1
                else:
                    if hi[axis] == size[axis] - 1:
                        continue
                    a[axis] = b[axis] = hi[axis] + 1
                slab = box_sum(sums, a, b)
                volume = (b[0] - a[0] + 1) * (b[1] - a[1] + 1) * (b[2] - a[2] + 1)
                if slab == volume and slab > best_gain:
                    best, best_gain = (axis, side), slab
        if best is None:
            return lo, hi
        axis, side = best
        if side < 0:
            lo[axis] -= 1
        else:
            hi[axis] += 1


def residual_boxes(mask: np.ndarray, components: int, bounding: bool = True, grown: int = 1,
                   ) -> list[tuple[list[int], list[int]]]:
    """(lo, hi) inclusive voxel bounds for the ``components`` largest 6-connected components of a
    3D bool mask, largest first: each component's bounding box (if ``bounding``), then up to
    ``grown`` boxes grown inside it, each from the deepest voxel (taxicab distance to the mask's
    outside) that the boxes grown before do not cover."""
    labels, n = ndimage.label(mask)
    if n == 0:
        return []
    sizes = np.bincount(labels.ravel())[1:]
    slices = ndimage.find_objects(labels)
    depth = ndimage.distance_transform_cdt(mask, metric="taxicab")
    sums = prefix_sums(mask)
    out = []
    for k in np.argsort(-sizes, kind="stable")[:components]:
        sl = slices[k]
        start = [s.start for s in sl]
        if bounding:
            out.append((start, [s.stop - 1 for s in sl]))
        left = labels[sl] == k + 1                       # component voxels no grown box covers yet
        for _ in range(grown):
            if not left.any():
                break
            inside = np.where(left, depth[sl], -1)
            seed = np.add(np.unravel_index(int(inside.argmax()), inside.shape), start)
            lo, hi = grow_box(sums, seed)
            out.append((lo, hi))
            left[tuple(slice(max(a - s, 0), max(b + 1 - s, 0)) for a, b, s in zip(lo, hi, start))] = False
    return out
