"""Boxes where a residual says a primitive helps: connected components of a 3D voxel mask.

Insertion candidate generators of voxel domains use these: for the largest
6-connected components of a mask (e.g. target voxels a program misses), the
component's bounding box, and the largest box grown inside the component
from its deepest voxel (a bounding box alone is useless where a component
wraps around a shape, like the empty space around a chair inside its box).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage


def prefix_sums(mask: np.ndarray) -> np.ndarray:
    """Summed-volume table of a 3D mask: entry [i, j, k] counts mask[:i, :j, :k] (shape + 1 per axis).

    int32 (a 32^3 mask counts at most 32,768), summed in place: 2.4x the int64 cumulative sums it replaces.
    """
    out = np.zeros(tuple(n + 1 for n in mask.shape), dtype=np.int32)
    inner = out[1:, 1:, 1:]
    np.cumsum(mask, 0, dtype=np.int32, out=inner)
    np.cumsum(inner, 1, out=inner)
    np.cumsum(inner, 2, out=inner)
    return out


def grow_box(sums: np.ndarray, seed: Sequence[int]) -> tuple[list[int], list[int]]:
    """Grow a box from ``seed`` one face at a time while the new slab lies entirely in the mask.

    ``sums``: the mask's summed-volume table. At each step the face whose slab
    adds the most voxels grows (the first of -x, +x, -y, +y, -z, +z on a tie). Returns (lo, hi), inclusive
    voxel bounds. (Written out face by face, with the table read through ``ndarray.item``: a search grows
    hundreds of boxes, each a dozen steps of six slab sums.)
    """
    n0, n1, n2 = (n - 1 for n in sums.shape)
    at = sums.item

    def count(a0: int, a1: int, a2: int, b0: int, b1: int, b2: int) -> int:
        """Mask voxels in [a0, b0) x [a1, b1) x [a2, b2)."""
        return (at(b0, b1, b2) - at(a0, b1, b2) - at(b0, a1, b2) - at(b0, b1, a2)
                + at(a0, a1, b2) + at(a0, b1, a2) + at(b0, a1, a2) - at(a0, a1, a2))

    l0, l1, l2 = (int(v) for v in seed)
    h0, h1, h2 = l0, l1, l2
    while True:
        e0, e1, e2 = h0 + 1, h1 + 1, h2 + 1               # exclusive upper bounds
        yz, xz, xy = (e1 - l1) * (e2 - l2), (e0 - l0) * (e2 - l2), (e0 - l0) * (e1 - l1)   # slab volumes
        best, gain = -1, 0
        # a slab grows the box only if every voxel of it is in the mask (its count is its volume)
        if l0 > 0:
            c = count(l0 - 1, l1, l2, l0, e1, e2)
            if c == yz and c > gain:
                best, gain = 0, c
        if h0 < n0 - 1:
            c = count(e0, l1, l2, e0 + 1, e1, e2)
            if c == yz and c > gain:
                best, gain = 1, c
        if l1 > 0:
            c = count(l0, l1 - 1, l2, e0, l1, e2)
            if c == xz and c > gain:
                best, gain = 2, c
        if h1 < n1 - 1:
            c = count(l0, e1, l2, e0, e1 + 1, e2)
            if c == xz and c > gain:
                best, gain = 3, c
        if l2 > 0:
            c = count(l0, l1, l2 - 1, e0, e1, l2)
            if c == xy and c > gain:
                best, gain = 4, c
        if h2 < n2 - 1:
            c = count(l0, l1, e2, e0, e1, e2 + 1)
            if c == xy and c > gain:
                best, gain = 5, c
        if best < 0:
            return [l0, l1, l2], [h0, h1, h2]
        if best == 0:
            l0 -= 1
        elif best == 1:
            h0 += 1
        elif best == 2:
            l1 -= 1
        elif best == 3:
            h1 += 1
        elif best == 4:
            l2 -= 1
        else:
            h2 += 1


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
