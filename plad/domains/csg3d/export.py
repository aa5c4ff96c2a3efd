"""csg3d outputs: marching-cubes mesh, three orthographic views, and OpenSCAD text.

Coordinates are the programs' voxel index units: voxel (i, j, k) of a grid
indexed [x, y, z] is centered at (i, j, k), so a mesh or SCAD solid lies in
[-0.5, 31.5]^3 with y up, like the ShapeAssembly views (same view axes).
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from plad.domains.csg3d.tokens import program_tree


def mesh_arrays(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(32, 32, 32) bool [x, y, z] -> vertices (V, 3) float64, triangles (F, 3) int64.

    Marching cubes at level 0.5 of the occupancy, padded by one empty voxel on
    every side so that shapes touching the border are closed.
    """
    from skimage.measure import marching_cubes

    grid = np.asarray(grid, dtype=bool)
    if not grid.any():
        raise ValueError("the shape is empty: there is no surface to write")
    padded = np.pad(grid, 1).astype(np.float32)
    verts, faces, _, _ = marching_cubes(padded, level=0.5)
    return verts.astype(np.float64) - 1.0, faces.astype(np.int64)     # undo the padding offset


def save_mesh(grid: np.ndarray, path: str | Path) -> None:
    """Write the surface of a voxel grid as a triangle mesh (.ply or .obj), atomically."""
    from plad.data.mesh import write_mesh

    write_mesh(*mesh_arrays(grid), path)


def save_views(grid: np.ndarray, path: str | Path, title: str | None = None) -> None:
    """PNG with three orthographic depth views (front: x-y, side: z-y, top: x-z) of a voxel grid."""
    from plad.data.pictures import save_views as views

    views(grid, path, title)


_SCAD_OPS = {"union": "union", "inter": "intersection", "diff": "difference"}


def _num(v: float) -> str:
    return f"{v:g}"


def to_scad(ids: Sequence[int], fn: int = 48) -> str:
    """An OpenSCAD file equivalent to a valid csg3d program.

    ``cuboid x y z dx dy dz`` -> ``translate([x, y, z]) cube([dx, dy, dz], center = true);``,
    ``ellipsoid ...`` -> ``translate([x, y, z]) scale([dx/2, dy/2, dz/2]) sphere(r = 1);``,
    operators -> ``union() {A B}``, ``intersection() {A B}``, ``difference() {A B}``
    (OpenSCAD's difference subtracts its later children from the first, like ``diff A B``).
    ``fn`` is the sphere tessellation (``$fn``).
    """
    from plad.domains.csg3d.tokens import format_program

    lines = [
        f"// csg3d program: {format_program(ids)}",
        "// Units: voxels. Voxel (i, j, k) of the 32^3 grid indexed [x, y, z] is centered at (i, j, k);",
        "// the program's shape is the set of voxel centers inside this solid.",
        f"$fn = {fn};",
    ]

    def emit(node, indent: int) -> None:
        pad = "  " * indent
        if node[0] in ("cuboid", "ellipsoid"):
            x, y, z, dx, dy, dz = node[1]
            move = f"translate([{x}, {y}, {z}])"
            if node[0] == "cuboid":
                lines.append(f"{pad}{move} cube([{dx}, {dy}, {dz}], center = true);")
            else:
                lines.append(f"{pad}{move} scale([{_num(dx / 2)}, {_num(dy / 2)}, {_num(dz / 2)}]) sphere(r = 1);")
            return
        lines.append(f"{pad}{_SCAD_OPS[node[0]]}() {{")
        emit(node[1], indent + 1)
        emit(node[2], indent + 1)
        lines.append(f"{pad}}}")

    emit(program_tree(ids), 0)
    return "\n".join(lines) + "\n"
