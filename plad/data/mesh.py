"""Writing triangle meshes (.ply, .obj) with open3d, for the 3D domains' outputs."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_mesh(verts: np.ndarray, faces: np.ndarray, path: str | Path) -> None:
    """Write vertices (V, 3) and triangles (F, 3) to ``path`` (format by suffix), with vertex normals."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(verts, dtype=np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int64)))
    mesh.compute_vertex_normals()
    if not o3d.io.write_triangle_mesh(str(path), mesh):
        raise OSError(f"open3d could not write {path}")
