"""Triangle meshes: written (.ply, .obj) for the 3D domains' outputs, and read (.obj, .ply, .off, .stl) for
the user's shapes, at a cost bounded by their size.

Writing: the file's bytes are made here (binary PLY as open3d writes it, or OBJ text, both with vertex
normals) and written by :func:`plad.fsutil.atomic_write`, so that a full disk is an error and never a
truncated mesh in place of the old one (open3d's writers ignore a short write).

Reading (:func:`read_mesh`): a mesh of at most :data:`MAX_TRIANGLES` triangles and :data:`MAX_VERTICES`
vertices, counted from the file's header where the format has one (PLY, OFF, binary STL) before anything
is loaded; a larger one is refused in one line. Whether it is watertight (closed: every edge shared by
two triangles) is decided in time linear in its size (:func:`closed`); open3d's
own check (:meth:`is_watertight`, which also looks for self-intersections at a cost that grows with the
square of the triangles: 2.3 s at 40,000) runs only on meshes of at most :data:`SELF_INTERSECTION_MAX`
triangles, and the reader says when it was skipped.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

#: the most triangles of a mesh read (a 2,000,000-triangle PLY is about 38 MB; voxelizing it takes seconds)
MAX_TRIANGLES = 2_000_000
#: the most vertices of a mesh read
MAX_VERTICES = 3_000_000
#: the most triangles whose self-intersections are checked (open3d's check is quadratic: about 0.6 s here)
SELF_INTERSECTION_MAX = 20_000


class MeshError(ValueError):
    """A mesh cannot be read within the bounds; the message is one line (without the file name)."""


# ---- writing ---------------------------------------------------------------------------------------------
def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals: the sums of the adjacent triangles' area-weighted normals (open3d's
    ``compute_vertex_normals``)."""
    verts, faces = np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    tri = verts[faces] if len(faces) else np.zeros((0, 3, 3))
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(verts)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def mesh_bytes(verts: np.ndarray, faces: np.ndarray, suffix: str) -> bytes:
    """The file of a mesh with vertex normals: ``.ply`` (binary little-endian, as open3d writes it) or ``.obj``
    (text). Raises ``ValueError`` for another suffix."""
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    normals = vertex_normals(verts, faces)
    suffix = suffix.lower()
    if suffix == ".ply":
        header = ("ply\nformat binary_little_endian 1.0\ncomment Created by PLAD\n"
                  f"element vertex {len(verts)}\n"
                  + "".join(f"property double {n}\n" for n in ("x", "y", "z", "nx", "ny", "nz"))
                  + f"element face {len(faces)}\nproperty list uchar uint vertex_indices\nend_header\n")
        vertex = np.concatenate([verts, normals], 1).astype("<f8")
        face = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<u4", (3,))])
        face["n"], face["v"] = 3, faces
        return header.encode() + vertex.tobytes() + face.tobytes()
    if suffix == ".obj":
        lines = [f"# Created by PLAD\n# number of vertices: {len(verts)}\n# number of triangles: {len(faces)}\n"]
        for v, n in zip(verts, normals):
            lines.append(f"v {v[0]:.17g} {v[1]:.17g} {v[2]:.17g}\nvn {n[0]:.17g} {n[1]:.17g} {n[2]:.17g}\n")
        lines += [f"f {a}//{a} {b}//{b} {c}//{c}\n" for a, b, c in (faces + 1).tolist()]
        return "".join(lines).encode()
    raise ValueError(f"unsupported mesh type {suffix or '(none)'!r}; use .ply or .obj")


def write_mesh(verts: np.ndarray, faces: np.ndarray, path: str | Path) -> None:
    """Write vertices (V, 3) and triangles (F, 3) to ``path`` (format by suffix: .ply or .obj), with vertex
    normals, atomically (:func:`plad.fsutil.atomic_write`: a failure is a one-line ``WriteError``)."""
    from plad.fsutil import atomic_write_bytes

    path = Path(path)
    atomic_write_bytes(path, mesh_bytes(verts, faces, path.suffix))


# ---- reading ---------------------------------------------------------------------------------------------
def declared_size(path: Path) -> tuple[int | None, int | None]:
    """(vertices, triangles) a mesh file declares in its header, read without loading it (None: the format
    declares none, or the header is not readable: open3d then decides). A polygon of an OFF or PLY file
    counts as one triangle here (a lower bound)."""
    suffix = path.suffix.lower()
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
            if suffix == ".stl":
                if len(head) >= 84 and not head[:5].lower().startswith(b"solid"):
                    return None, int.from_bytes(head[80:84], "little")
                return None, None   # ASCII STL: counted while read (its size is bounded by the file's)
            if suffix == ".ply":
                end = head.find(b"end_header")
                text = head[:end if end >= 0 else len(head)].decode("latin-1")
                vertices = re.search(r"^element\s+vertex\s+(\d+)", text, re.M)
                faces = re.search(r"^element\s+face\s+(\d+)", text, re.M)
                return (int(vertices.group(1)) if vertices else None, int(faces.group(1)) if faces else None)
            if suffix == ".off":
                words = []
                for line in head.decode("latin-1").splitlines():
                    line = line.split("#", 1)[0].strip()
                    if line:
                        words += line.split()
                    if len(words) >= 3 and words[0].upper().endswith("OFF") and len(words) >= 4 or \
                            len(words) >= 3 and not words[0].upper().endswith("OFF"):
                        break
                if words and words[0].upper().endswith("OFF"):
                    words = words[1:]
                if len(words) >= 2 and words[0].isdigit() and words[1].isdigit():
                    return int(words[0]), int(words[1])
    except OSError:
        pass
    return None, None


def check_size(vertices: int | None, triangles: int | None) -> None:
    """:class:`MeshError` when a mesh has more than :data:`MAX_VERTICES` vertices or :data:`MAX_TRIANGLES`
    triangles."""
    if triangles is not None and triangles > MAX_TRIANGLES:
        raise MeshError(f"the mesh has {triangles:,} triangles, more than the limit of {MAX_TRIANGLES:,}; "
                        "simplify it first (e.g. quadric decimation)")
    if vertices is not None and vertices > MAX_VERTICES:
        raise MeshError(f"the mesh has {vertices:,} vertices, more than the limit of {MAX_VERTICES:,}; "
                        "simplify it first")


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, triangles (F, 3) int64) of a mesh file, within the bounds of the module
    (:class:`MeshError`, one line, otherwise: too large, no triangles, a triangle naming no vertex,
    non-finite coordinates)."""
    import open3d as o3d

    path = Path(path)
    check_size(*declared_size(path))
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    mesh = o3d.io.read_triangle_mesh(str(path))
    if not mesh.has_triangles():
        raise MeshError("no triangles: not a readable mesh")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    check_size(len(verts), len(faces))
    if faces.min() < 0 or faces.max() >= len(verts):
        raise MeshError("a triangle names a vertex the mesh does not have")
    if not np.isfinite(verts).all():
        raise MeshError("the mesh has non-finite vertex coordinates")
    return verts, faces


def closed(faces: np.ndarray) -> bool:
    """Whether the triangles make a closed surface: every edge shared by exactly two triangles (open3d's
    edge-manifold test without boundary; orientation is not needed to tell inside from outside by counting
    crossings), no triangle degenerate. Linear in the triangles (a sort of the edges)."""
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return False
    if ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])).any():
        return False
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    keys = np.sort(edges[:, 0] * (int(faces.max()) + 1) + edges[:, 1])
    _, counts = np.unique(keys, return_counts=True)
    return bool((counts == 2).all())


def watertight(verts: np.ndarray, faces: np.ndarray) -> tuple[bool, str | None]:
    """(whether the mesh is watertight, a note or None): closed (:func:`closed`), and, for a mesh of at most
    :data:`SELF_INTERSECTION_MAX` triangles, open3d's full check (vertex-manifold, not self-intersecting);
    a larger closed mesh is taken as watertight without that check, which the note says."""
    if not closed(faces):
        return False, None
    if len(faces) > SELF_INTERSECTION_MAX:
        return True, (f"the mesh is closed; with {len(faces):,} triangles (over {SELF_INTERSECTION_MAX:,}) it was "
                      "not checked for self-intersections")
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(faces))
    return bool(mesh.is_watertight()), None
