"""`plad infer` on the user's shapes: a tiny untrained model made here, registered in a temporary
MLflow store; PNG, a folder with bad files, meshes; outputs and metrics consistent with `plad score`."""
from __future__ import annotations

import csv
import re

import numpy as np
import pytest
import torch
from PIL import Image

from plad.data.inputs import FIT_2D, fit_canvas, read_inputs, voxelize_mesh
from plad.domains import get_domain
from plad.serve.cli import main
from tests.conftest import REPO_ROOT

PROGRAM_2D = "c(32,32,16)s(40,40,12)-$"
PROGRAM_3D = "union cuboid 12 10 16 10 8 12 ellipsoid 20 18 16 12 12 14"


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory, tiny_checkpoint):
    root = tmp_path_factory.mktemp("models")
    return {name: tiny_checkpoint(root / f"{name}.pt", name) for name in ("csg2d", "csg3d")}


@pytest.fixture(scope="module")
def registry(tmp_path_factory, checkpoints):
    """A temporary MLflow store whose plad-csg2d@champion is the tiny 2D model."""
    import mlflow

    from plad import tracking
    from plad.tracking import StageRun

    root = tmp_path_factory.mktemp("registry")
    mp = pytest.MonkeyPatch()
    uri = f"sqlite:///{root / 'mlflow.db'}"
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mp.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    mlflow.set_tracking_uri(uri)
    with StageRun("report", "csg2d", {}, root / "run") as run:
        version = run.log_model(checkpoints["csg2d"], registered_name="plad-csg2d").rsplit("/", 1)[1]
    tracking.set_champion("plad-csg2d", version)
    yield uri
    mp.undo()


def render_2d(text: str) -> np.ndarray:
    domain = get_domain("csg2d")
    return domain.execute(torch.tensor([domain.parse(text)]))[0].numpy()


def save_png(mask: np.ndarray, path, scale: int = 1) -> None:
    """Black shape on white, upscaled by ``scale`` (so the input is not canvas-sized)."""
    img = np.where(mask, 0, 255).astype(np.uint8).repeat(scale, 0).repeat(scale, 1)
    Image.fromarray(img, mode="L").save(path)


def the_run(out):
    """The one run folder a `plad infer --out out` made (each run writes into its own)."""
    (run,) = [p for p in out.iterdir() if p.is_dir()]
    return run


def rows_of(out) -> list[dict]:
    with open(out / "results.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def scored(capsys, domain: str, pred, target) -> float:
    capsys.readouterr()
    assert main(["score", domain, "--pred", str(pred), "--target", str(target)]) == 0
    return float(capsys.readouterr().out.split()[0])


# ---- reading shapes -------------------------------------------------------------------------------------
def test_fit_rule_crops_scales_and_centers():
    mask = np.zeros((100, 200), bool)
    mask[30:70, 20:180] = True                       # a 160 x 40 bar
    out = fit_canvas(mask, (64, 64))
    rows, cols = np.nonzero(out)
    assert cols.max() - cols.min() + 1 == FIT_2D and rows.max() - rows.min() + 1 == 11
    assert (cols.min() + cols.max()) / 2 == pytest.approx(31.5, abs=0.5)
    assert (rows.min() + rows.max()) / 2 == pytest.approx(31.5, abs=0.5)


def test_canvas_sized_images_are_only_binarized_either_polarity(tmp_path):
    shape = render_2d(PROGRAM_2D)
    save_png(shape, tmp_path / "black_on_white.png")
    save_png(~shape, tmp_path / "white_on_black.png")
    items = read_inputs([tmp_path], (64, 64))
    assert [it.name for it in items] == ["black_on_white", "white_on_black"]
    for it in items:
        assert it.error is None and np.array_equal(it.shape, shape) and it.notes == []


def test_watertight_mesh_voxelizes_by_voxel_centers(tmp_path):
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(1.0, 0.5, 0.25)
    o3d.io.write_triangle_mesh(str(tmp_path / "box.obj"), box)
    grid, notes = voxelize_mesh(tmp_path / "box.obj", (32, 32, 32))
    # normalized: x spans the grid, y the middle 16 voxel centers, z the middle 8
    expected = np.zeros((32, 32, 32), bool)
    expected[:, 8:24, 12:20] = True
    assert notes == [] and np.array_equal(grid, expected)


def test_open_mesh_is_voxelized_by_its_surface_with_a_note(tmp_path):
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    tris = np.asarray(box.triangles)
    normals = np.asarray(box.compute_triangle_normals().triangle_normals)
    open_box = o3d.geometry.TriangleMesh(box.vertices, o3d.utility.Vector3iVector(tris[normals[:, 1] < 0.5]))
    o3d.io.write_triangle_mesh(str(tmp_path / "open.ply"), open_box)             # no top face
    grid, notes = voxelize_mesh(tmp_path / "open.ply", (32, 32, 32))
    assert "not watertight" in notes[0] and "encloses no space" in notes[0]
    assert grid[:, 0, :].all() and not grid[1:-1, 5:-1, 1:-1].any()             # floor, hollow inside


# ---- plad infer ---------------------------------------------------------------------------------------
def test_infer_png_with_the_registered_champion(registry, tmp_path, capsys):
    save_png(render_2d(PROGRAM_2D), tmp_path / "drawing.png", scale=3)          # 192 x 192: fitted
    out = tmp_path / "out"
    assert main(["infer", "csg2d", str(tmp_path / "drawing.png"), "--beam", "3", "--out", str(out)]) == 0
    out = the_run(out)
    err = capsys.readouterr().err
    assert "model: models:/plad-csg2d@champion" in err
    assert re.search(r"1 of 1 shapes inferred and refined in \d+\.\d s", err)          # refined by default
    for suffix in (".txt", ".png", ".svg", ".input.npy", ".recon.npy"):
        assert (out / f"drawing{suffix}").is_file(), suffix
    (row,) = rows_of(out)
    assert row["status"] == "ok" and "fitted a 192x192 shape" in row["notes"]
    program = (out / "drawing.txt").read_text().strip()
    assert row["program"] == program
    # the program executes to the saved reconstruction, which scores as reported against the input
    assert np.array_equal(np.load(out / "drawing.recon.npy"), render_2d(program))
    value = scored(capsys, "csg2d", out / "drawing.recon.npy", out / "drawing.input.npy")
    assert float(row["chamfer"]) == pytest.approx(value, abs=1e-5)
    assert (out / "drawing.svg").read_text().startswith("<svg")


def test_folder_with_bad_files_processes_the_others(registry, tmp_path, capsys):
    folder = tmp_path / "shapes"
    folder.mkdir()
    save_png(render_2d(PROGRAM_2D), folder / "good.png")
    (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    Image.fromarray(np.full((64, 64), 255, np.uint8)).save(folder / "blank.png")
    (folder / "readme.txt").write_text("not a shape")                        # unsupported: skipped
    out = tmp_path / "out"
    status = main(["infer", "csg2d", str(folder), "--beam", "2", "--out", str(out)])
    out = the_run(out)
    captured = capsys.readouterr()
    assert status == 2
    assert "broken.png: not a readable image" in captured.err
    assert "blank.png: the image is a single color" in captured.err
    rows = {r["name"]: r for r in rows_of(out)}
    assert set(rows) == {"blank", "broken", "good"}
    assert rows["good"]["status"] == "ok" and float(rows["good"]["chamfer"]) >= 0
    assert rows["broken"]["status"] == rows["blank"]["status"] == "error"
    assert (out / "good.svg").is_file() and not (out / "broken.txt").exists()
    assert "good.png: chamfer" in captured.out


def test_refining_every_beam_candidate_is_never_worse_than_the_best_of_beam_only(tmp_path):
    """--effort best against default on the shipped 2D model, a beam of 2 and one example drawing: best keeps
    the best of the beam's candidates each refined on its own, never worse than default's; every value is the one
    its written program scores when executed again."""
    from plad.model.checkpoint import load_model
    from plad.model.decode import infer_programs
    from plad.rewrite import RefineConfig, refine, search_config
    from plad.rewrite.evaluate import Scorer
    from plad.serve.infer import Refinement, infer_items, refinement
    from plad.shipped import shipped_model

    domain = get_domain("csg2d")
    # default: what infer always did, grafting from the domain's library since it has one
    grafting = RefineConfig(graft=15, graft_library="shipped")
    assert refinement(domain) == Refinement(grafting)
    assert refinement(domain, "best") == Refinement(grafting, all_candidates=True)
    assert refinement(domain, "fast") == Refinement(search_config(domain, effort="fast").refine)
    # a domain's refine_defaults: ShapeAssembly removes parts (a tree domain prunes instead)
    sa = get_domain("shapeassembly")
    assert refinement(sa) == Refinement(RefineConfig(remove=True))
    assert refinement(sa, "best") == Refinement(RefineConfig(remove=True), all_candidates=True)
    model = load_model(shipped_model("csg2d").checkpoint, torch.device("cpu"), expect_domain="csg2d")[0]
    values = {}
    for effort in ("default", "best"):
        (item,) = read_inputs([str(REPO_ROOT / "examples" / "csg2d" / "house.png")], tuple(domain.shape))
        out = tmp_path / effort
        (result,) = infer_items(model, domain, [item], 2, out, progress=False, refine=refinement(domain, effort))
        assert result.ok
        program = domain.parse((out / "house.txt").read_text().strip())
        target = torch.from_numpy(np.load(out / "house.input.npy")[None])
        assert float(Scorer(domain, target).values([program])[0]) == result.value     # re-verified by execution
        values[effort] = result.value
    assert not domain.metric.better(torch.tensor(values["default"]), torch.tensor(values["best"]))
    # best is the best of the candidates refined one by one
    beam = infer_programs(model, domain, target, 2).beam
    alone = [float(refine(domain, [beam.program(0, k)], target, RefineConfig()).values[0]) for k in range(2)]
    assert values["best"] == domain.metric.best_value(alone)


def test_infer_takes_an_effort_level_but_not_without_refinement(registry, tmp_path, capsys):
    save_png(render_2d(PROGRAM_2D), tmp_path / "a.png")
    for effort in ("best", "fast", "default"):
        status = main(["infer", "csg2d", str(tmp_path / "a.png"), "--no-refine", "--effort", effort,
                       "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err.strip().splitlines()
        assert status == 2 and len(err) == 1 and "--no-refine" in err[0], err
    status = main(["infer", "csg2d", str(tmp_path / "a.png"), "--effort", "quick", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "'quick': expected one of fast, default, best" in err[0], err
    assert not (tmp_path / "out").exists()                   # refused before any work
    assert main(["infer", "csg2d", str(tmp_path / "a.png"), "--beam", "2", "--effort", "best",
                 "--out", str(tmp_path / "out")]) == 0
    assert "1 of 1 shapes inferred and refined" in capsys.readouterr().err


def test_infer_obj_mesh_with_a_checkpoint(checkpoints, tmp_path, capsys):
    mesh = tmp_path / "part.obj"
    assert main(["execute", "csg3d", PROGRAM_3D, "-o", str(mesh)]) == 0
    out = tmp_path / "out"
    assert main(["infer", "csg3d", str(mesh), "--model", str(checkpoints["csg3d"]), "--beam", "2", "--no-refine",
                 "--out", str(out)]) == 0
    out = the_run(out)
    for suffix in (".txt", ".png", ".scad", ".input.npy", ".recon.npy"):
        assert (out / f"part{suffix}").is_file(), suffix
    (row,) = rows_of(out)
    # the tiny model is untrained: its program may execute to nothing, which has no mesh but a note
    empty = not np.load(out / "part.recon.npy").any()
    assert (out / "part.ply").is_file() != empty
    assert ("executes to an empty shape" in row["notes"]) == empty
    target = np.load(out / "part.input.npy")
    assert target.shape == (32, 32, 32) and target.any()
    value = scored(capsys, "csg3d", out / "part.recon.npy", out / "part.input.npy")
    assert float(row["iou"]) == pytest.approx(value, abs=1e-5)
    assert (out / "part.scad").read_text().startswith("// csg3d program:")


def test_a_model_of_another_domain_is_refused(checkpoints, tmp_path, capsys):
    save_png(render_2d(PROGRAM_2D), tmp_path / "a.png")
    status = main(["infer", "csg2d", str(tmp_path / "a.png"), "--model", str(checkpoints["csg3d"]),
                   "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    # a checkpoint that cannot be used is a failure of the run's data (exit status 1, plad.errors), and the
    # model is resolved before the run's folder is made: nothing is left behind
    assert status == 1 and "a csg3d model, not a csg2d one" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_a_missing_registered_model_is_one_line(registry, tmp_path, capsys):
    save_png(render_2d(PROGRAM_2D), tmp_path / "a.png")
    status = main(["infer", "csg2d", str(tmp_path / "a.png"), "--model", "models:/plad-nothing@champion",
                   "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1 and len(err) == 1 and "models:/plad-nothing@champion: not found" in err[0]


def test_svg_export_draws_the_program(tmp_path):
    """The SVG, rasterized by cairo, matches the executor: exactly for circles and squares, and up to
    edge pixels of triangles in general (IoU over sampled programs)."""
    cairosvg = pytest.importorskip("cairosvg")
    import io

    from plad.domains.csg2d.export import to_svg

    domain = get_domain("csg2d")

    def raster(ids):
        png = cairosvg.svg2png(bytestring=to_svg(ids).encode(), output_width=64, output_height=64)
        return np.asarray(Image.open(io.BytesIO(png)).convert("L")) < 128

    for text in ("c(32,32,16)$", "s(32,32,16)$", "c(32,32,16)s(40,40,12)+$", "c(32,32,16)s(40,40,12)*$",
                 "c(32,32,16)s(40,40,12)-$", "s(32,32,24)c(32,32,16)s(40,40,12)--$"):
        ids = domain.parse(text)
        assert np.array_equal(raster(ids), render_2d(text)), text
    programs = domain.sample(200, np.random.default_rng(3))
    executed = domain.execute(torch.tensor([p + [0] * (14 - len(p)) for p in programs])).numpy()
    ious = [(raster(p) & e).sum() / (raster(p) | e).sum() for p, e in zip(programs, executed)]
    assert np.median(ious) > 0.99 and np.mean(ious) > 0.97
