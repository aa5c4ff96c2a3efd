"""Mesh (.ply/.obj, :func:`plad.data.mesh.write_mesh`) and three-view PNG output of oriented cuboids, written
atomically."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from plad.data.datasets.partnet.voxels import corners
from plad.data.pictures import VIEWS as _VIEWS  # the view axes of every 3D picture

# triangles of a cuboid over the corner order of voxels.corners (index = 4 sx + 2 sy + sz,
# with s = 0 for -, 1 for +), outward facing (counter-clockwise seen from outside)
_QUADS = [(0, 1, 3, 2), (4, 6, 7, 5),      # x-, x+
          (0, 4, 5, 1), (2, 3, 7, 6),      # y-, y+
          (0, 2, 6, 4), (1, 5, 7, 3)]      # z-, z+
_TRIS = np.array([t for a, b, c, d in _QUADS for t in ((a, b, c), (a, c, d))], dtype=np.int64)


def mesh_arrays(cuboids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 15) cuboids -> vertices (8n, 3) float64, triangles (12n, 3) int64."""
    v = corners(cuboids)                                                  # (n, 8, 3)
    faces = _TRIS[None] + 8 * np.arange(len(v))[:, None, None]
    return v.reshape(-1, 3), faces.reshape(-1, 3)


def save_mesh(cuboids: np.ndarray, path: str | Path) -> None:
    """Write the cuboids as one triangle mesh (.ply or .obj), atomically."""
    from plad.data.mesh import write_mesh

    write_mesh(*mesh_arrays(cuboids), path)


def save_views(cuboids: np.ndarray, path: str | Path, title: str | None = None) -> None:
    """PNG with three orthographic views (front: x-y, side: z-y, top: x-z) of the cuboids.

    Faces are drawn back to front (painter's algorithm) and shaded by how much
    they face the viewer. Uses matplotlib's Agg backend (no display needed).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    verts = corners(cuboids).reshape(-1, 3)
    quads = np.array(_QUADS)[None] + 8 * np.arange(len(verts) // 8)[:, None, None]
    tri = verts[quads.reshape(-1, 4)]                                     # (6n, 4, 3) faces
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    lo, hi = (verts.min(0), verts.max(0)) if len(verts) else (np.zeros(3) - .5, np.zeros(3) + .5)
    pad = 0.05 * float((hi - lo).max() or 1.0)
    fig, axs = plt.subplots(1, 3, figsize=(9, 3.3))
    for ax, (name, h, v, d, sign) in zip(axs, _VIEWS):
        facing = sign * normals[:, d]
        keep = facing > 1e-9
        depth = sign * tri[keep][:, :, d].mean(1)
        order = np.argsort(depth)
        polys = tri[keep][order][:, :, [h, v]]
        if v == 2:                                                        # top view: +z (front) down
            polys = polys * np.array([1, -1])
        shade = 0.35 + 0.55 * facing[keep][order]
        ax.add_collection(PolyCollection(polys, facecolors=np.stack([shade * .55, shade * .7, shade], 1),
                                         edgecolors="k", linewidths=0.3))
        ys = (lo[v] - pad, hi[v] + pad) if v != 2 else (-hi[v] - pad, -lo[v] + pad)
        ax.set_xlim(lo[h] - pad, hi[h] + pad)
        ax.set_ylim(*ys)
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    from plad.data.pictures import save_figure

    save_figure(fig, path, dpi=100)
