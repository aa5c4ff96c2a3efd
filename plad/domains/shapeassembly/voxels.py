"""Voxelization of oriented cuboids at 32^3 (spec section 5).

Grid: voxel (i, j, k) has center ``((i+.5)/32 - .5, (j+.5)/32 - .5, (k+.5)/32 - .5)``
for (x, y, z), arrays are indexed [x, y, z], y is up. A voxel is occupied iff
its center c satisfies ``|(c - p).u_a| <= max(|d_a|/2, 0.55/32) + 1e-6`` for the
three unit axes u_a of some cuboid (center p, dims d). The 0.55-voxel minimum
half-extent keeps thin parts (shelves, slats) at least one voxel layer thick.

Real (PartNet) shapes are first normalized by the tight bounds of all cuboid
corners (:func:`normalization`); the discretized domain's programs already
live in that centered unit cube and are voxelized as they are.

Speed: instead of testing every voxel against every cuboid, each cuboid only
tests the voxels inside its own axis-aligned bounding box; all (cuboid,
voxel) candidates of a whole batch are enumerated in one flat tensor.
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
    dev = cuboids.device
    c = cuboids.to(torch.float64)
    n = c.shape[0]
    grids = torch.zeros(batch * res ** 3, dtype=torch.bool, device=dev)
    if n == 0:
        return grids.view(batch, res, res, res), torch.zeros(0, dtype=torch.long, device=dev)
    p = c[:, 0:3]
    u = c[:, 3:12].reshape(n, 3, 3)
    u = u / u.norm(dim=2, keepdim=True)                                    # (N, 3 axes, 3)
    half = torch.clamp(c[:, 12:15].abs() / 2, min=min_half) + TOL          # (N, 3)
    # axis-aligned extent of each cuboid -> inclusive voxel index ranges per axis
    ext = (half[:, :, None] * u.abs()).sum(1)                              # (N, 3)
    lo = torch.ceil((p - ext + 0.5) * res - 0.5).clamp(0, res).long()
    hi = torch.floor((p + ext + 0.5) * res - 0.5).clamp(-1, res - 1).long()
    size = (hi - lo + 1).clamp(min=0)                                      # (N, 3)
    count = size.prod(1)
    # flat enumeration of every (cuboid, voxel in its box) candidate
    which = torch.repeat_interleave(torch.arange(n, device=dev), count)   # (M,)
    start = torch.cumsum(count, 0) - count
    local = torch.arange(which.shape[0], device=dev) - start[which]
    sx, sy = size[which, 0], size[which, 1]
    idx = torch.stack([local % sx, (local // sx) % sy, local // (sx * sy)], 1) + lo[which]   # (M, 3)
    centers = (idx.to(torch.float64) + 0.5) / res - 0.5
    rel = torch.einsum("mad,md->ma", u[which], centers - p[which])       # (M, 3) coordinates along the axes
    inside = (rel.abs() <= half[which]).all(1)
    which, idx = which[inside], idx[inside]
    flat = owner[which] * res ** 3 + (idx[:, 0] * res + idx[:, 1]) * res + idx[:, 2]
    grids[flat] = True
    # voxels covered exactly once in their shape belong uniquely to their cuboid
    cover = torch.bincount(flat, minlength=batch * res ** 3)
    unique = torch.bincount(which[cover[flat] == 1], minlength=n)
    return grids.view(batch, res, res, res), unique


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
