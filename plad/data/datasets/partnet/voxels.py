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
    """
    c = cuboids.detach().cpu().numpy().astype(np.float64)
    own = owner.detach().cpu().numpy()
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
    count = np.zeros((batch, res, res, res), dtype=np.int16)
    boxes = []
    for m in range(n):
        (x0, y0, z0), (x1, y1, z1) = lo[m], hi[m] + 1
        if x1 <= x0 or y1 <= y0 or z1 <= z0:
            boxes.append(None)
            continue
        # (c - p) per axis over the box, then the three projections by broadcasting:
        # proj_a[i, j, k] = dx[i] u_a,x + dy[j] u_a,y + dz[k] u_a,z   (box shape)
        d = [centers[x0:x1] - p[m, 0], centers[y0:y1] - p[m, 1], centers[z0:z1] - p[m, 2]]
        if np.count_nonzero(u[m]) == 3:
            # axes along the grid axes (the common case): the test separates into three
            # 1-D tests; the zero terms of the general sum are exact, so this is the same test
            k = np.abs(u[m]).argmax(1)                                     # grid axis of each cuboid axis
            ok = [None, None, None]
            for a in range(3):
                ok[k[a]] = np.abs(d[k[a]] * u[m, a, k[a]]) <= half[m, a]
            inside = ok[0][:, None, None] & ok[1][None, :, None] & ok[2][None, None, :]
        else:
            dx, dy, dz = d[0][:, None, None], d[1][None, :, None], d[2][None, None, :]
            inside = None
            for a in range(3):
                ua = u[m, a]
                proj = dx * ua[0] + dy * ua[1] + dz * ua[2]
                ok_a = np.abs(proj) <= half[m, a]
                inside = ok_a if inside is None else inside & ok_a
        count[own[m], x0:x1, y0:y1, z0:z1] += inside
        boxes.append(inside)
    # voxels covered exactly once in their shape belong uniquely to their cuboid
    unique = np.zeros(n, dtype=np.int64)
    for m, inside in enumerate(boxes):
        if inside is not None:
            (x0, y0, z0), (x1, y1, z1) = lo[m], hi[m] + 1
            unique[m] = int((inside & (count[own[m], x0:x1, y0:y1, z0:z1] == 1)).sum())
    return torch.from_numpy(count > 0), torch.from_numpy(unique)


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
