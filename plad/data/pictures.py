"""Pictures of shapes, for any domain: 2D canvases as images, 3D voxel grids as three depth views.

Two kinds: matplotlib figures with titles (:func:`save_comparison`,
:func:`save_views`: ``plad infer``, 3D exports) and plain pixel grids of
target | reconstruction pairs (:func:`pair_grid`, :func:`save_png`: the
evaluation stage's ``grid.png``).

The view convention (shared with the ShapeAssembly cuboid views): grids are
indexed [x, y, z] with y up; ``front`` looks along -z (x right, y up),
``side`` along +x (z right, y up), ``top`` along -y (x right, +z down).
Uses matplotlib's Agg backend (no display needed).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from plad.fsutil import atomic_write, atomic_write_bytes

#: (name, horizontal axis, vertical axis, depth axis, depth sign): views look along -sign * depth
VIEWS = (("front", 0, 1, 2, 1), ("side", 2, 1, 0, -1), ("top", 0, 2, 1, 1))

# the tint of shaded 3D views (ShapeAssembly's cuboid views use the same)
_TINT = np.array([0.55, 0.7, 1.0])


def depth_views(grid: np.ndarray) -> dict[str, np.ndarray]:
    """Per view of :data:`VIEWS`: a (vertical, horizontal) float image holding the depth index
    (0 nearest the viewer) of the first occupied voxel along the view direction, NaN where the
    ray misses."""
    grid = np.asarray(grid, dtype=bool)
    out = {}
    for name, h, v, d, sign in VIEWS:
        occ = np.transpose(grid, (v, h, d))                              # (vertical, horizontal, depth)
        if sign > 0:                                                     # the viewer is on the +d side
            occ = occ[:, :, ::-1]
        first = occ.argmax(axis=2).astype(np.float64)
        first[~occ.any(axis=2)] = np.nan
        out[name] = first
    return out


def _show_view(ax, depth: np.ndarray, n: int, vertical_axis: int) -> None:
    shade = 1.0 - 0.65 * np.nan_to_num(depth, nan=0.0) / max(n - 1, 1)
    rgb = shade[..., None] * _TINT
    rgb[np.isnan(depth)] = 1.0                                          # white background
    # y up in the front/side views; in the top view +z (the front) is down
    top = vertical_axis == 2
    ax.imshow(rgb, origin="upper" if top else "lower", interpolation="nearest",
              extent=(-0.5, n - 0.5, n - 0.5, -0.5) if top else (-0.5, n - 0.5, -0.5, n - 0.5))


def save_views(grid: np.ndarray, path: str | Path, title: str | None = None) -> None:
    """PNG with the three depth views of one voxel grid."""
    save_comparison([("", grid)], path, title)


def save_comparison(panels: Sequence[tuple[str, np.ndarray]], path: str | Path, title: str | None = None) -> None:
    """PNG of shapes side by side: 2D canvases in one row; 3D grids one row each (three views).

    ``panels``: (label, bool array) pairs, all 2D or all 3D.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arrays = [np.asarray(a, dtype=bool) for _, a in panels]
    dims = {a.ndim for a in arrays}
    if len(dims) != 1 or dims - {2, 3}:
        raise ValueError(f"expected all 2D or all 3D shapes, got dimensions {sorted(dims)}")
    if dims == {2}:
        fig, axs = plt.subplots(1, len(panels), figsize=(3 * len(panels), 3.3), squeeze=False)
        for ax, (label, _), a in zip(axs[0], panels, arrays):
            ax.imshow(~a, cmap="gray", vmin=0, vmax=1, interpolation="nearest")   # black shape on white
            ax.set_title(label)
            ax.set_xticks([])
            ax.set_yticks([])
    else:
        fig, axs = plt.subplots(len(panels), 3, figsize=(9, 3.3 * len(panels)), squeeze=False)
        for row, (label, _), a in zip(axs, panels, arrays):
            views = depth_views(a)
            for ax, (name, _h, v, _d, _s) in zip(row, VIEWS):
                _show_view(ax, views[name], a.shape[0], v)
                ax.set_title(f"{label}: {name}" if label else name)
                ax.set_xticks([])
                ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def save_figure(fig, path: str | os.PathLike, **savefig) -> None:
    """A matplotlib figure as the PNG file ``path``, written atomically (:func:`plad.fsutil.atomic_write`: a
    full disk is a one-line ``WriteError``, never a truncated picture); the figure is closed."""
    import io

    import matplotlib.pyplot as plt

    try:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", **savefig)
    finally:
        plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


# -- pixel grids of (target | reconstruction) pairs ----------------------------------------------
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
    """An image array (uint8, (H, W) or (H, W, 3)) as a PNG file, written atomically."""
    atomic_write(path, lambda fh: Image.fromarray(image).save(fh, format="PNG"))


def save_npy(array: np.ndarray, path: str | os.PathLike) -> None:
    """An array as a ``.npy`` file, written atomically (through a buffer: ``np.save`` on a real file writes
    past Python's file object)."""
    import io

    buf = io.BytesIO()
    np.save(buf, array)
    atomic_write_bytes(path, buf.getvalue())
