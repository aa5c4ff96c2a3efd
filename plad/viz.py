"""Pictures: grids of target | reconstruction pairs."""
from __future__ import annotations

import os

import numpy as np

from plad.fsutil import atomic_write


def _as_image(shape: np.ndarray) -> np.ndarray:
    """A 2D canvas as is; a 3D voxel grid as three orthographic projections side by side."""
    if shape.ndim == 2:
        return shape
    views = [shape.any(axis=a) for a in range(3)]
    gap = np.zeros((shape.shape[1], 2), dtype=bool)
    return np.concatenate([views[0], gap, views[1], gap, views[2]], axis=1)


def pair_grid(targets: np.ndarray, recons: np.ndarray, columns: int = 4, scale: int = 2) -> np.ndarray:
    """uint8 RGB image: rows of (target | reconstruction) cells, targets in black, reconstructions in blue."""
    cells = []
    for t, r in zip(targets, recons):
        ti, ri = _as_image(t), _as_image(r)
        h, w = ti.shape
        cell = np.full((h + 4, 2 * w + 12, 3), 255, dtype=np.uint8)
        cell[2:2 + h, 2:2 + w][ti] = (0, 0, 0)
        cell[2:2 + h, w + 6:w + 6 + w][ri] = (30, 80, 200)
        cell[:, w + 3:w + 5] = (200, 200, 200)  # separator
        cells.append(cell)
    if not cells:
        return np.full((8, 8, 3), 255, dtype=np.uint8)
    ch, cw, _ = cells[0].shape
    rows = (len(cells) + columns - 1) // columns
    grid = np.full((rows * (ch + 4), columns * (cw + 4), 3), 230, dtype=np.uint8)
    for i, cell in enumerate(cells):
        r, c = divmod(i, columns)
        grid[r * (ch + 4):r * (ch + 4) + ch, c * (cw + 4):c * (cw + 4) + cw] = cell
    return grid.repeat(scale, 0).repeat(scale, 1)


def save_png(image: np.ndarray, path: str | os.PathLike) -> None:
    from PIL import Image

    atomic_write(path, lambda fh: Image.fromarray(image).save(fh, format="PNG"))
