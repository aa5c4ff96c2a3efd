"""csg3d command line: ``plad execute csg3d`` outputs and ``plad export csg3d --format scad``."""
import re

import numpy as np
import pytest
import torch

from plad.data.pictures import depth_views
from plad.domains import get_domain
from plad.domains.csg3d.export import mesh_arrays, to_scad
from plad.serve.cli import main
from tests.reference.csg3d_render import render

DOMAIN = get_domain("csg3d")
PROGRAM = "diff union cuboid 16 10 16 24 6 24 cuboid 16 20 16 6 18 6 ellipsoid 16 22 16 10 10 9"


def test_execute_npy_is_the_executed_grid(tmp_path, capsys):
    out = tmp_path / "shape.npy"
    assert main(["execute", "csg3d", PROGRAM, "-o", str(out)]) == 0
    grid = np.load(out)
    assert grid.dtype == bool and grid.shape == (32, 32, 32)
    assert np.array_equal(grid, render(PROGRAM))
    assert f"{int(grid.sum())} of 32768 voxels occupied" in capsys.readouterr().err


def test_execute_reads_a_program_file(tmp_path):
    src = tmp_path / "prog.txt"
    src.write_text("union\n  cuboid 8 8 8 6 6 6\n  ellipsoid 20 20 20 9 9 9\n")
    assert main(["execute", "csg3d", str(src), "-o", str(tmp_path / "s.npy")]) == 0
    assert np.array_equal(np.load(tmp_path / "s.npy"), render(src.read_text()))


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_execute_mesh_bounds_the_voxels(tmp_path, suffix):
    import open3d as o3d

    out = tmp_path / f"shape{suffix}"
    assert main(["execute", "csg3d", PROGRAM, "-o", str(out)]) == 0
    mesh = o3d.io.read_triangle_mesh(str(out))
    verts = np.asarray(mesh.vertices)
    assert len(verts) > 0 and len(np.asarray(mesh.triangles)) > 0
    grid = render(PROGRAM)
    occ = np.argwhere(grid)
    # the level-0.5 surface passes half-way between an occupied voxel center and an empty one
    assert np.allclose(verts.min(0), occ.min(0) - 0.5) and np.allclose(verts.max(0), occ.max(0) + 0.5)


def test_mesh_of_a_box_is_closed_and_has_its_volume():
    import open3d as o3d

    grid = render("cuboid 16 16 16 8 6 4")   # 9 x 7 x 5 voxel centers
    verts, faces = mesh_arrays(grid)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(faces))
    assert mesh.is_watertight()
    # marching cubes cuts the box's 12 edges and 8 corners but keeps the faces at +-0.5
    assert 8 * 6 * 4 < abs(mesh.get_volume()) < 9 * 7 * 5


def test_execute_png_and_its_views(tmp_path):
    from PIL import Image

    out = tmp_path / "shape.png"
    assert main(["execute", "csg3d", PROGRAM, "-o", str(out)]) == 0
    with Image.open(out) as im:
        assert im.size == (900, 330)
        pixels = np.asarray(im.convert("RGB")).reshape(-1, 3)
    assert (pixels[:, 2] > pixels[:, 0] + 60).any()                  # the shape's blue tint is drawn
    views = depth_views(render("cuboid 10 20 5 3 5 1"))             # x 9..11, y 18..22, z 5
    front = views["front"]                                           # rows y, columns x, looking along -z
    hit = ~np.isnan(front)
    assert np.array_equal(np.argwhere(hit.any(1)).flatten(), np.arange(18, 23))
    assert np.array_equal(np.argwhere(hit.any(0)).flatten(), np.arange(9, 12))
    assert np.all(front[hit] == 31 - 5)                              # z = 5 seen from the +z side
    top = views["top"]                                               # rows z, columns x, looking along -y
    assert np.all(top[~np.isnan(top)] == 31 - 22)


@pytest.mark.parametrize("args, message", [
    (["execute", "csg3d", "cuboid 16 16 16 8 8 40", "-o", "x.npy"], "invalid csg3d program: token 6 '40'"),
    (["execute", "csg3d", "union cuboid 1 1 1 2 2 2", "-o", "x.npy"], "missing its second operand"),
    (["execute", "csg3d", PROGRAM, "-o", "x.stl"], "unsupported output type '.stl'"),
    (["execute", "csg3d", "diff cuboid 8 8 8 4 4 4 cuboid 8 8 8 6 6 6", "-o", "x.ply"], "the shape is empty"),
    (["export", "csg3d", PROGRAM, "--format", "stl"], "unknown export format 'stl' for csg3d; known: ply, scad"),
    (["export", "csg2d", "c(32,32,16)$", "--format", "scad"], "unknown export format 'scad' for csg2d; known: svg"),
    (["export", "csg3d", "cube 1 2 3", "--format", "scad"], "token 0 'cube' is not a csg3d token"),
])
def test_cli_errors_are_one_line(tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and err.startswith("plad: error:")


# ---- OpenSCAD export -----------------------------------------------------------------------------
_PRIM = re.compile(r"translate\(\[(\d+), (\d+), (\d+)\]\) (?:cube\(\[(\d+), (\d+), (\d+)\], center = true\)"
                   r"|scale\(\[([\d.]+), ([\d.]+), ([\d.]+)\]\) sphere\(r = 1\));")
_OPS = {"union() {": "union", "intersection() {": "inter", "difference() {": "diff"}


def scad_to_program(scad: str) -> str:
    """Read our SCAD output back to program text (one statement per line), checking its structure."""
    lines = [ln.strip() for ln in scad.splitlines() if ln.strip() and not ln.strip().startswith("//")]
    assert lines[0] == "$fn = 48;"
    words, children = [], [0]   # children[i]: operands seen so far in the i-th open block (0: top level)
    for ln in lines[1:]:
        if ln == "}":
            assert children.pop() == 2, "every Boolean block has exactly two children"
            continue
        children[-1] += 1
        if ln in _OPS:
            words.append(_OPS[ln])
            children.append(0)
            continue
        m = _PRIM.fullmatch(ln)
        assert m, ln
        g = m.groups()
        if g[3] is not None:
            words += ["cuboid", *g[:6]]
        else:
            words += ["ellipsoid", *g[:3], *(f"{2 * float(v):g}" for v in g[6:])]
    assert children == [1], "one top-level solid and balanced braces"
    return " ".join(words)


def test_scad_of_a_small_program():
    scad = to_scad(DOMAIN.parse(PROGRAM))
    assert scad.count("{") == scad.count("}") == 2
    body = [ln for ln in scad.splitlines() if not ln.startswith("//")]
    assert body == [
        "$fn = 48;",
        "difference() {",
        "  union() {",
        "    translate([16, 10, 16]) cube([24, 6, 24], center = true);",
        "    translate([16, 20, 16]) cube([6, 18, 6], center = true);",
        "  }",
        "  translate([16, 22, 16]) scale([5, 5, 4.5]) sphere(r = 1);",
        "}",
    ]


def test_scad_of_a_lone_primitive_and_intersection():
    assert to_scad(DOMAIN.parse("ellipsoid 3 4 5 7 8 31")).splitlines()[-1] == \
        "translate([3, 4, 5]) scale([3.5, 4, 15.5]) sphere(r = 1);"
    scad = to_scad(DOMAIN.parse("inter cuboid 1 2 3 4 5 6 cuboid 6 5 4 3 2 1"))
    assert "intersection() {" in scad and scad.count("cube(") == 2


def test_scad_structure_matches_200_sampled_programs():
    for ids in DOMAIN.sample(200, np.random.default_rng(5)):
        text = DOMAIN.format(ids)
        scad = to_scad(ids)
        assert scad.count("{") == scad.count("}")
        assert scad.count("cube(") == text.split().count("cuboid")
        assert scad.count("sphere(") == text.split().count("ellipsoid")
        assert scad_to_program(scad) == text


def test_export_cli_writes_the_file_or_stdout(tmp_path, capsys):
    out = tmp_path / "shape.scad"
    assert main(["export", "csg3d", PROGRAM, "--format", "scad", "-o", str(out)]) == 0
    assert out.read_text() == to_scad(DOMAIN.parse(PROGRAM))
    assert main(["export", "csg3d", PROGRAM, "--format", "scad"]) == 0
    assert capsys.readouterr().out == out.read_text()


def test_export_files_of_a_program_that_executes_to_nothing(tmp_path):
    """Disjoint intersection: no surface to mesh, so only the OpenSCAD file is written (inference keeps going)."""
    ids = DOMAIN.parse("inter cuboid 6 6 6 4 4 4 cuboid 26 26 26 4 4 4")
    assert not DOMAIN.execute(torch.tensor([ids]))[0].any()
    files = DOMAIN.export_files(ids, tmp_path / "empty")
    assert files == [tmp_path / "empty.scad"] and files[0].read_text().count("intersection") == 1
    assert not (tmp_path / "empty.ply").exists()
    ids = DOMAIN.parse(PROGRAM)
    assert [f.suffix for f in DOMAIN.export_files(ids, tmp_path / "full")] == [".ply", ".scad"]
