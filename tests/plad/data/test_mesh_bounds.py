"""A mesh is read at a cost bounded by its size, or refused in one line (issue 53, reproduction 6): the
triangles are counted from the header (PLY, OFF, binary STL) before anything is loaded; whether a mesh is
closed is decided in linear time and agrees with open3d's check on random meshes; open3d's quadratic
self-intersection check runs only on small meshes (a note says when it was skipped). Meshes are written by
PLAD itself (the bytes open3d reads back), so that a full disk is an error, never a truncated file."""
from __future__ import annotations

import time

import numpy as np
import open3d as o3d
import pytest

from plad.data import mesh as meshes
from plad.data.inputs import read_file
from plad.data.mesh import MAX_TRIANGLES, closed, mesh_bytes, watertight

GRID = (32, 32, 32)


def sphere(resolution: int = 12):
    m = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution)
    return np.asarray(m.vertices), np.asarray(m.triangles)


def box():
    m = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 0.5)
    return np.asarray(m.vertices), np.asarray(m.triangles)


@pytest.mark.parametrize("seed", range(8))
def test_closed_agrees_with_open3d_on_random_damage(seed):
    rng = np.random.default_rng(seed)
    verts, faces = (sphere(int(rng.integers(4, 16))) if seed % 2 else box())
    faces = faces.copy()
    damage = seed % 4
    if damage == 1:                                  # a hole
        faces = np.delete(faces, rng.integers(len(faces)), 0)
    elif damage == 2:                                # a flipped triangle
        k = rng.integers(len(faces))
        faces[k] = faces[k][::-1]
    elif damage == 3:                                # a duplicated triangle
        faces = np.concatenate([faces, faces[:1]])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(faces))
    ours = closed(faces)
    assert ours == (damage in (0, 2))               # a flipped triangle leaves the surface closed
    assert not ours or mesh.is_watertight()          # closed and small: open3d agrees it is watertight
    assert watertight(verts, faces)[0] == mesh.is_watertight()


@pytest.mark.parametrize("suffix, header", [
    (".ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
             b"property float z\nelement face 999999999\nproperty list uchar int vertex_indices\nend_header\n"),
    (".off", b"OFF\n3 999999999 0\n0 0 0\n1 0 0\n0 1 0\n"),
    (".stl", b"\0" * 80 + (999_999_999).to_bytes(4, "little") + b"\0" * 50),
])
def test_a_mesh_declaring_too_many_triangles_is_refused_from_its_header(tmp_path, suffix, header):
    path = tmp_path / f"huge{suffix}"
    path.write_bytes(header)
    began = time.perf_counter()
    (item,) = read_file(path, GRID)
    assert time.perf_counter() - began < 2
    assert item.error == f"the mesh has 999,999,999 triangles, more than the limit of {MAX_TRIANGLES:,}; " \
                         "simplify it first (e.g. quadric decimation)"


def test_a_large_closed_mesh_skips_the_quadratic_check_and_says_so(tmp_path, monkeypatch):
    verts, faces = sphere(30)
    path = tmp_path / "ball.ply"
    path.write_bytes(mesh_bytes(verts, faces, ".ply"))
    (small,) = read_file(path, GRID)                 # checked in full: no note
    assert small.error is None and small.notes == []
    monkeypatch.setattr(meshes, "SELF_INTERSECTION_MAX", 100)

    def quadratic(self):
        raise AssertionError("the self-intersection check ran on a large mesh")
    monkeypatch.setattr(o3d.geometry.TriangleMesh, "is_watertight", quadratic)
    (large,) = read_file(path, GRID)
    assert large.error is None and np.array_equal(large.shape, small.shape)
    assert large.notes == [f"the mesh is closed; with {len(faces):,} triangles (over 100) it was not checked for "
                           "self-intersections"]
    monkeypatch.setattr(meshes, "MAX_TRIANGLES", len(faces) - 1)   # a file without a count: after reading
    (refused,) = read_file(path, GRID)
    assert refused.error.startswith(f"the mesh has {len(faces):,} triangles, more than the limit")


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_the_written_meshes_read_back(tmp_path, suffix):
    verts, faces = sphere(10)
    path = tmp_path / f"m{suffix}"
    path.write_bytes(mesh_bytes(verts, faces, suffix))
    back = o3d.io.read_triangle_mesh(str(path))
    assert len(back.triangles) == len(faces) and back.has_vertex_normals()
    assert np.allclose(np.sort(np.asarray(back.vertices), 0), np.sort(verts, 0))
    with pytest.raises(ValueError, match="unsupported mesh type '.stl'"):
        mesh_bytes(verts, faces, ".stl")
