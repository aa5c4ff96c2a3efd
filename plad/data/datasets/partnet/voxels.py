"""Voxelization of oriented cuboids at 32^3 (docs/shapeassembly.md, "Voxelizing a real shape").

Grid: voxel (i, j, k) has center ``((i+.5)/32 - .5, (j+.5)/32 - .5, (k+.5)/32 - .5)``
for (x, y, z), arrays are indexed [x, y, z], y is up. A voxel is occupied iff
its center c satisfies ``|(c - p).u_a| <= max(|d_a|/2, 0.55/32) + 1e-6`` for the
three unit axes u_a of some cuboid (center p, dims d). The 0.55-voxel minimum
half-extent keeps thin parts (shelves, slats) at least one voxel layer thick.

Real (PartNet) shapes are first normalized by the tight bounds of all cuboid
corners (:func:`normalization`); the discretized domain's programs already
live in that centered unit cube and are voxelized as they are.

Speed: instead of testing every voxel against every cuboid, each cuboid only
tests the voxels inside its own axis-aligned bounding box, and the three
projections over that box are sums of three broadcast 1-D vectors (the
projection is linear in the voxel indices), so no per-voxel gathers.
"""
from __future__ import annotations

import numpy as np
import torch

RES = 32
MIN_HALF = 0.55 / RES
TOL = 1e-6


def corners(cuboids: np.ndarray) -> np.ndarray:
    """(n, 15) cuboids -> (n, 8, 3) corners ``p +- |d_a|/2 u_a`` (axes re-normalized), float64."""
    c = np.asarray(cuboids, dtype=np.float64)
    axes = c[:, 3:12].reshape(-1, 3, 3)
    axes = axes / np.linalg.norm(axes, axis=2, keepdims=True)
    half = np.abs(c[:, 12:15]) / 2
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    return c[:, None, 0:3] + np.einsum("ka,na,nad->nkd", signs, half, axes)


def normalization(cuboids: np.ndarray) -> tuple[np.ndarray, float]:
    """Center m (3,) and scale s of the tight bounds of all corners: normalized = (P - m) / s."""
    pts = corners(cuboids).reshape(-1, 3)
    lo, hi = pts.min(0), pts.max(0)
    return (lo + hi) / 2, float((hi - lo).max())


def normalize(cuboids: np.ndarray, center: np.ndarray, scale: float) -> np.ndarray:
    """Apply (P - m) / s to the centers and dims of (n, 15) cuboids (axes unchanged), float64."""
    c = np.array(cuboids, dtype=np.float64)
    c[:, 0:3] = (c[:, 0:3] - center) / scale
    c[:, 12:15] = c[:, 12:15] / scale
    return c


def voxelize_batch(cuboids: torch.Tensor, owner: torch.Tensor, batch: int, min_half: float = MIN_HALF,
                   res: int = RES) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxelize cuboids of many shapes at once.

    cuboids: (N, 15) float (center, three axes, dims) already in the unit-cube frame;
    owner: (N,) long, the shape each cuboid belongs to (0 <= owner < batch).
    Returns (grids (batch, res, res, res) bool indexed [x, y, z], unique (N,) long:
    voxels of each cuboid that no other cuboid of its shape occupies).

    Cuboids whose axes lie along the grid axes (most of them) are voxelized together, a chunk of shapes at a
    time, as matrix products (:func:`_aligned_masks`, :func:`_chunk`); the others one at a time over their
    bounding boxes (:func:`_rotated_box`), the original algorithm. Both make exactly the original's booleans.
    """
    c = cuboids.detach().cpu().numpy().astype(np.float64)
    own = owner.detach().cpu().numpy().astype(np.int64, copy=False)
    n = len(c)
    p = c[:, 0:3]
    u = c[:, 3:12].reshape(n, 3, 3)
    u = u / np.linalg.norm(u, axis=2, keepdims=True)                      # (N, 3 axes, 3)
    half = np.maximum(np.abs(c[:, 12:15]) / 2, min_half) + TOL             # (N, 3)
    # axis-aligned extent of each cuboid -> inclusive voxel index ranges per axis
    ext = (half[:, :, None] * np.abs(u)).sum(1)                            # (N, 3)
    lo = np.clip(np.ceil((p - ext + 0.5) * res - 0.5), 0, res).astype(np.int64)
    hi = np.clip(np.floor((p + ext + 0.5) * res - 0.5), -1, res - 1).astype(np.int64)
    centers = (np.arange(res) + 0.5) / res - 0.5                           # (res,) voxel centers per axis
    aligned, grid_axis = _grid_aligned(u)
    fast = np.flatnonzero(aligned)
    masks = _aligned_masks(p[fast], u[fast], half[fast], lo[fast], hi[fast], grid_axis[fast], centers)
    slots = _slots(own[fast], batch)                                       # (batch, K) rows of masks, -1: none
    rotated = np.flatnonzero(~aligned)
    rotated = rotated[np.argsort(own[rotated], kind="stable")]            # by shape, then index
    starts = np.searchsorted(own[rotated], np.arange(batch + 1))           # shape b's: rotated[starts[b]:starts[b+1]]
    grids = torch.empty((batch, res, res, res), dtype=torch.bool)
    unique = np.zeros(n, dtype=np.int64)
    kernels = _compiled(len(fast))
    if kernels is not None:
        _counted(kernels, masks, slots, fast, rotated, starts, p, u, half, lo, hi, own, centers, grids, unique)
        return grids, torch.from_numpy(unique)
    step = max(1, min(_CHUNK_SHAPES, _CHUNK_CUBOIDS // max(slots.shape[1], 1)))
    for s0 in range(0, batch, step):
        s1 = min(s0 + step, batch)
        x, yz = _padded(masks, slots[s0:s1])
        # counts (S, res, res^2): aligned cuboids as x^T @ yz (exact: float32 sums of 0/1 below 2^24), then the
        # rotated ones' boxes added one by one
        counts = torch.bmm(x.transpose(1, 2), yz)
        count = counts.numpy().reshape(s1 - s0, res, res, res)            # shares memory with counts
        boxes = _add_boxes(rotated[starts[s0]:starts[s1]], p, u, half, lo, hi, own, centers, count, s0)
        torch.gt(counts, 0, out=grids[s0:s1].view(s1 - s0, res, res * res))
        # voxels covered exactly once in their shape belong uniquely to their cuboid; for aligned cuboid k with
        # E = (count == 1) (res, res^2): unique_k = sum_x x_k[x] (E @ yz_k)[x]
        once = torch.eq(counts, 1, out=torch.empty_like(counts))          # E as float32, in one pass
        per = torch.bmm(once, yz.transpose(1, 2))                          # (S, res, K)
        total = (per * x.transpose(1, 2)).sum(1).long().numpy()            # (S, K), exact integers
        real = slots[s0:s1] >= 0
        unique[fast[slots[s0:s1][real]]] = total[real]
        _box_unique(boxes, lo, hi, own, count, s0, unique)
    return grids, torch.from_numpy(unique)


def _add_boxes(cubes, p, u, half, lo, hi, own, centers, count, s0: int) -> list[tuple[int, np.ndarray]]:
    """The rotated cuboids ``cubes`` tested one at a time over their boxes (:func:`_rotated_box`), each box added
    into count (S, res, res, res) of the shapes from s0 on; returns (cuboid, box) of the nonempty ones."""
    boxes = []
    for m in cubes:
        inside = _rotated_box(p[m], u[m], half[m], lo[m], hi[m], centers)
        if inside is not None:
            (x0, y0, z0), (x1, y1, z1) = lo[m], hi[m] + 1
            count[own[m] - s0, x0:x1, y0:y1, z0:z1] += inside
            boxes.append((m, inside))
    return boxes


def _box_unique(boxes, lo, hi, own, count, s0: int, unique: np.ndarray) -> None:
    """unique[m] for each (cuboid m, box) of :func:`_add_boxes`: its voxels its shape covers exactly once."""
    for m, inside in boxes:
        (x0, y0, z0), (x1, y1, z1) = lo[m], hi[m] + 1
        unique[m] = int((inside & (count[own[m] - s0, x0:x1, y0:y1, z0:z1] == 1)).sum())


#: the grid-aligned cuboids' counts in compiled kernels (plad.data.datasets.partnet.voxels_compiled) where numba
#: is installed, the same booleans and unique counts: None when the process has earned it (plad.jit), True from
#: the first call, False never (the matrix products)
_COMPILED: bool | None = None
#: the matrix products' CPU seconds per aligned cuboid, for plad.jit's rule
_TENSOR_CUBOID_SECONDS = 1e-4


def _compiled(cuboids: int):
    """plad.data.datasets.partnet.voxels_compiled by plad.jit's rule for ``cuboids`` aligned cuboids, else None."""
    from plad import jit

    return jit.kernels("plad.data.datasets.partnet.voxels_compiled", _COMPILED, cuboids * _TENSOR_CUBOID_SECONDS)


def _counted(kernels, masks, slots, fast, rotated, starts, p, u, half, lo, hi, own, centers, grids, unique) -> None:
    """voxelize_batch's counts as integers, in chunks of shapes: the aligned cuboids added voxel by voxel
    (compiled), the rotated ones' boxes as before; then the grids and every cuboid's unique voxels."""
    batch, res = grids.shape[0], grids.shape[1]
    out = grids.numpy().reshape(batch, res ** 3)
    for s0 in range(0, batch, _CHUNK_SHAPES):
        s1 = min(s0 + _CHUNK_SHAPES, batch)
        count = np.zeros((s1 - s0, res, res, res), dtype=np.int32)
        chunk = np.ascontiguousarray(slots[s0:s1])
        total = np.zeros(chunk.shape, dtype=np.int64)
        kernels.aligned(masks, chunk, count, total, False)
        mine = rotated[starts[s0]:starts[s1]]
        # compiled: finite axes, and not the original's separable branch with two axes along one grid axis (on
        # which it failed): those take the numpy test, as before
        ok = np.isfinite(u[mine]).all((1, 2))
        separable = np.count_nonzero(u[mine], axis=(1, 2)) == 3
        ok &= ~separable | (np.sort(np.abs(np.nan_to_num(u[mine])).argmax(2), 1) == np.arange(3)).all(1)
        compiled, shape_of = mine[ok], own[mine[ok]] - s0
        once = np.zeros(len(compiled), dtype=np.int64)
        kernels.rotated(p, u, half, lo, hi, centers, compiled, shape_of, count, once, False)
        boxes = _add_boxes(mine[~ok], p, u, half, lo, hi, own, centers, count, s0)
        np.greater(count.reshape(s1 - s0, -1), 0, out=out[s0:s1])
        kernels.aligned(masks, chunk, count, total, True)
        real = chunk >= 0
        unique[fast[chunk[real]]] = total[real]
        kernels.rotated(p, u, half, lo, hi, centers, compiled, shape_of, count, once, True)
        unique[compiled] = once
        _box_unique(boxes, lo, hi, own, count, s0, unique)


#: bounds on one chunk of :func:`voxelize_batch`: at most this many shapes ((S, res^3) float32 counts, 2 MiB at
#: res 32: small chunks stay in cache, 16 measured fastest of 8..128) and shapes x the most aligned cuboids of one
#: shape ((S, K, res^2) float32 masks, 32 MiB)
_CHUNK_SHAPES = 16
_CHUNK_CUBOIDS = 8192


def _grid_aligned(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which cuboids (N,) bool have their three axes along three distinct grid axes, and that grid axis of
    each cuboid axis (N, 3) long.

    The original took its separable test when ``count_nonzero(u) == 3``; with unit rows that is one nonzero
    per row. Rows of NaN (a zero axis), or two axes along one grid axis (on which the original failed), are
    left to the per-cuboid path, which does exactly what the original did with them.
    """
    k = np.abs(np.nan_to_num(u)).argmax(2)                                 # (N, 3)
    ok = (np.count_nonzero(u, axis=(1, 2)) == 3) & np.isfinite(u).all((1, 2))
    ok &= (np.sort(k, axis=1) == np.arange(3)).all(1)
    return ok, k


def _aligned_masks(p, u, half, lo, hi, k, centers) -> np.ndarray:
    """Per-axis occupancy of M grid-aligned cuboids: (M, 3 grid axes, res) bool.

    The original's separable test, vectorized: along grid axis g, with a the cuboid axis along it,
    voxel i passes when ``|(center_i - p_g) * u[a, g]| <= half[a]`` and i lies in the cuboid's index range
    [lo_g, hi_g] (the original tested only inside that box). The same float64 operations on the same numbers,
    so the same booleans; the cuboid's voxels are the outer product of its three masks.
    """
    m = len(p)
    res = len(centers)
    axis_of = np.argsort(k, axis=1)                                        # (M, 3): cuboid axis along grid axis g
    rows = np.arange(m)[:, None]
    ug = u[rows, axis_of, np.arange(3)[None, :]]                           # (M, 3) u[a(g), g]
    hg = half[rows, axis_of]                                               # (M, 3) half[a(g)]
    d = centers[None, None, :] - p[:, :, None]                             # (M, 3, res)
    ok = np.abs(d * ug[:, :, None]) <= hg[:, :, None]
    idx = np.arange(res)
    ok &= (idx >= lo[:, :, None]) & (idx <= hi[:, :, None])
    return ok


def _slots(own: np.ndarray, batch: int) -> np.ndarray:
    """Cuboids by shape for the batched matrix products: (batch, K) long, the index (into ``own``) of each
    shape's k-th cuboid, -1 past its last; K is the most cuboids of one shape."""
    count = np.bincount(own, minlength=batch)
    slots = np.full((batch, int(count.max()) if len(own) else 0), -1, dtype=np.int64)
    order = np.argsort(own, kind="stable")
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    slots[own[order], np.arange(len(order)) - first[own[order]]] = order
    return slots


def _padded(masks: np.ndarray, slots: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """(S, K) slots -> x masks (S, K, res) and yz masks (S, K, res^2) float32, zero for a slot of -1."""
    res = masks.shape[-1]
    pad = np.concatenate([masks, np.zeros((1, 3, res), bool)])            # row -1: the empty cuboid
    sm = torch.from_numpy(pad[slots]).float()                              # (S, K, 3, res)
    x = sm[:, :, 0]
    yz = (sm[:, :, 1, :, None] * sm[:, :, 2, None, :]).flatten(2)          # (S, K, res^2)
    return x, yz


def _rotated_box(p, u, half, lo, hi, centers) -> np.ndarray | None:
    """The original per-cuboid test of one cuboid over its bounding box [lo, hi]: bool (box shape), or None for
    an empty box."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi + 1
    if x1 <= x0 or y1 <= y0 or z1 <= z0:
        return None
    # (c - p) per axis over the box, then the three projections by broadcasting:
    # proj_a[i, j, k] = dx[i] u_a,x + dy[j] u_a,y + dz[k] u_a,z   (box shape)
    d = [centers[x0:x1] - p[0], centers[y0:y1] - p[1], centers[z0:z1] - p[2]]
    if np.count_nonzero(u) == 3:
        # the original's separable branch, for axes it took as grid-aligned that _grid_aligned does not
        k = np.abs(u).argmax(1)
        ok = [None, None, None]
        for a in range(3):
            ok[k[a]] = np.abs(d[k[a]] * u[a, k[a]]) <= half[a]
        return ok[0][:, None, None] & ok[1][None, :, None] & ok[2][None, None, :]
    dx, dy, dz = d[0][:, None, None], d[1][None, :, None], d[2][None, None, :]
    inside = None
    for a in range(3):
        ua = u[a]
        proj = dx * ua[0] + dy * ua[1] + dz * ua[2]
        ok_a = np.abs(proj) <= half[a]
        inside = ok_a if inside is None else inside & ok_a
    return inside


def voxelize(cuboids: np.ndarray, min_half: float = MIN_HALF, normalized: bool = False) -> np.ndarray:
    """One shape's (n, 15) cuboids -> (32, 32, 32) bool [x, y, z].

    Unless ``normalized``, the shape is first normalized by its tight bounds
    (the convention for real PartNet shapes).
    """
    c = np.asarray(cuboids, dtype=np.float64)
    if not normalized and len(c):
        c = normalize(c, *normalization(c))
    grids, _ = voxelize_batch(torch.from_numpy(c), torch.zeros(len(c), dtype=torch.long), 1, min_half)
    return grids[0].numpy()
