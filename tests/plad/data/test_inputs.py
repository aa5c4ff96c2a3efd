"""One reader for every command (issue 30): the repository's own examples, any image size, colour, alpha and
16-bit images, meshes, a prediction placed in its target's frame, and batches with bad shapes, read alike by
`plad score`, `search`, `refine` and `infer` (plad.data.inputs)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from plad.data.inputs import fit_canvas, read_array, read_file, read_inputs
from plad.domains import get_domain
from plad.serve.cli import main
from tests.conftest import REPO_ROOT

EXAMPLES = REPO_ROOT / "examples"
GEAR = "c(32,32,24)s(32,32,12)-c(32,32,8)+$"


def render(text: str) -> np.ndarray:
    domain = get_domain("csg2d")
    return domain.execute(torch.tensor([domain.parse(text)]))[0].numpy()


def last_value(capsys) -> float:
    return float(capsys.readouterr().out.strip().splitlines()[-1].split()[-1])


def test_every_command_reads_the_repository_s_256_pixel_drawing_as_infer_does(tmp_path, capsys):
    gear = EXAMPLES / "csg2d" / "gear.png"
    (want,) = read_inputs([gear], (64, 64))
    (got,) = read_file(gear, (64, 64))
    assert got.error is None and np.array_equal(got.shape, want.shape) and "fitted a 256x256" in got.notes[0]
    # the drawing is the gear program at 4x: its 64x64 execution, placed in the drawing's frame, scores 0
    np.save(tmp_path / "gear64.npy", render(GEAR))
    Image.fromarray(render(GEAR).astype(np.uint8) * 255).save(tmp_path / "gear64.png")
    for pred in ("gear64.npy", "gear64.png"):
        assert main(["score", "csg2d", "--pred", str(tmp_path / pred), "--target", str(gear)]) == 0
        assert last_value(capsys) == 0.0
    assert main(["search", "csg2d", str(gear), "--set", "insertions=3", "--set", "refine.rounds=0"]) == 0
    assert "fitted a 256x256 shape" in capsys.readouterr().err
    assert main(["refine", "csg2d", "c(32,32,16)$", "--target", str(gear), "--set", "refine.rounds=1"]) == 0
    before, after = capsys.readouterr().out.strip().splitlines()[-1].split()[1::2]
    assert float(after) < float(before)


def test_polarity_alpha_and_16_bit_images_read_the_same_shape(tmp_path, capsys):
    shape = render(GEAR)
    Image.fromarray(np.where(shape, 0, 255).astype(np.uint8)).save(tmp_path / "black_on_white.png")
    Image.fromarray(np.where(shape, 255, 0).astype(np.uint8)).save(tmp_path / "white_on_black.png")
    rgba = np.zeros((64, 64, 4), np.uint8)
    rgba[..., 3] = np.where(shape, 255, 0)                     # black everywhere: only the alpha draws
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    Image.fromarray(np.where(shape, 60000, 300).astype(np.uint16)).save(tmp_path / "wide.png")
    assert Image.open(tmp_path / "wide.png").mode == "I;16"   # 300 and 60000 would both clip to 255 in 8 bits
    for name in ("black_on_white", "white_on_black", "rgba", "wide"):
        (item,) = read_file(tmp_path / f"{name}.png", (64, 64))
        assert item.error is None and np.array_equal(item.shape, shape), name
    # score: a black-on-white prediction against a white-on-black target is the same shape
    assert main(["score", "csg2d", "--pred", str(tmp_path / "black_on_white.png"),
                 "--target", str(tmp_path / "white_on_black.png")]) == 0
    assert last_value(capsys) == 0.0


def test_fitting_is_pil_s_box_resize_of_the_crop_centered():
    """The fit rule on the whole source (so that a prediction can go where its target went) draws exactly what
    cropping, PIL's box resize and centering draw: the canvas the network was always shown."""
    rng = np.random.default_rng(3)
    for _ in range(150):
        h, w = rng.integers(3, 400, 2)
        mask = rng.random((h, w)) < rng.random()
        mask[rng.integers(0, h), rng.integers(0, w)] = True
        rows, cols = np.nonzero(mask)
        crop = mask[rows.min():rows.max() + 1, cols.min():cols.max() + 1]
        scale = 44 / max(crop.shape)
        nh, nw = max(1, round(crop.shape[0] * scale)), max(1, round(crop.shape[1] * scale))
        small = np.asarray(Image.fromarray(crop.astype(np.float32)).resize((nw, nh), Image.Resampling.BOX)) >= 0.5
        want = np.zeros((64, 64), bool)
        want[(64 - nh) // 2:(64 - nh) // 2 + nh, (64 - nw) // 2:(64 - nw) // 2 + nw] = small
        assert np.array_equal(fit_canvas(mask, (64, 64)), want), (h, w)


def test_a_prediction_is_placed_where_its_target_went(tmp_path, capsys):
    target = np.zeros((100, 200), bool)
    target[30:70, 20:180] = True
    pred = np.roll(target, 10, axis=1)                          # the same bar, moved 10 source pixels
    np.save(tmp_path / "t.npy", target)
    np.save(tmp_path / "p.npy", pred)
    (t,) = read_file(tmp_path / "t.npy", (64, 64))
    (p,) = read_file(tmp_path / "p.npy", (64, 64), target=False, frames=[t.frame])
    assert np.array_equal(t.shape, fit_canvas(target, (64, 64)))
    # fitted by itself the moved bar would be the target exactly; in the target's frame it is moved too
    cols = np.nonzero(p.shape.any(0))[0]
    assert cols.min() - np.nonzero(t.shape.any(0))[0].min() == round(10 * 44 / 160)
    np.save(tmp_path / "other.npy", np.zeros((100, 100), bool))
    assert main(["score", "csg2d", "--pred", str(tmp_path / "other.npy"), "--target", str(tmp_path / "t.npy")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "another aspect ratio than its target's 200x100" in err


def test_meshes_are_read_by_score_and_search(tmp_path, capsys):
    table = EXAMPLES / "csg3d" / "table.obj"
    assert main(["score", "csg3d", "--pred", str(table), "--target", str(table)]) == 0
    assert last_value(capsys) == 1.0
    (item,) = read_file(table, (32, 32, 32))
    (want,) = read_inputs([table], (32, 32, 32))
    assert item.error is None and np.array_equal(item.shape, want.shape)
    # a mesh prediction goes into its target mesh's frame; against a voxel grid target there is none
    np.save(tmp_path / "grid.npy", item.shape)
    assert main(["score", "csg3d", "--pred", str(table), "--target", str(tmp_path / "grid.npy")]) == 2
    assert "give the target as a mesh too" in capsys.readouterr().err


def test_a_batch_with_an_empty_a_full_and_a_nan_shape_processes_the_others(tmp_path, capsys):
    good = render("c(32,32,16)$")
    np.save(tmp_path / "batch.npy", np.stack([good, np.zeros_like(good), good, np.ones_like(good)]))
    assert main(["search", "csg2d", str(tmp_path / "batch.npy"), "--set", "insertions=2", "--set",
                 "refine.rounds=0", "-o", str(tmp_path / "found.txt")]) == 2
    captured = capsys.readouterr()
    assert "batch.npy [1]: the shape is empty" in captured.err and "batch.npy [3]: the shape fills" in captured.err
    assert captured.out.count("chamfer 0.000000") == 2 and "mean 0.000000" in captured.out
    lines = (tmp_path / "found.txt").read_text().split("\n")
    assert [bool(line) for line in lines[:4]] == [True, False, True, False]
    # score: the bad pairs print nan, the mean is over the others
    np.save(tmp_path / "preds.npy", np.stack([good] * 4))
    assert main(["score", "csg2d", "--pred", str(tmp_path / "preds.npy"), "--target",
                 str(tmp_path / "batch.npy")]) == 2
    out = capsys.readouterr().out.split()
    assert out[:4] == ["0.000000", "nan", "0.000000", "nan"] and out[-1] == "0.000000"
    # the same rule for an in-memory array (the pyfunc model's input)
    arrays = np.stack([good, np.zeros_like(good), np.where(good, np.nan, 0.0), good.astype(float)])
    items = read_array(arrays, (64, 64))
    assert [it.error is None for it in items] == [True, False, False, True]
    assert items[2].error == "the array holds NaN or infinite values" and items[2].where == "<array> [2]"


def test_npy_inputs_have_the_image_pixel_cap_from_their_header(tmp_path, capsys):
    big = tmp_path / "big.npy"
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1), bool))
    header["shape"] = (16000, 16000)
    with open(big, "wb") as fh:                                 # a header only: the cap is read from it
        np.lib.format.write_array_header_1_0(fh, header)
    (item,) = read_file(big, (64, 64))
    assert item.error == "the array is 16000x16000 pixels, more than the limit of 25,000,000 pixels"


def test_the_full_shapeassembly_language_is_exported_and_refused_by_refine_with_the_way_on(tmp_path, capsys):
    chair = EXAMPLES / "shapeassembly" / "chair.txt"
    assert main(["export", "shapeassembly", str(chair), "--format", "ply", "-o", str(tmp_path / "chair.ply")]) == 0
    assert (tmp_path / "chair.ply").read_bytes().startswith(b"ply")
    assert main(["refine", "shapeassembly", str(chair), "--target",
                 str(EXAMPLES / "shapeassembly" / "table.npy")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "full ShapeAssembly language" in err and "plad search shapeassembly" in err


@pytest.mark.parametrize("domain, fmt", [("csg2d", "svg"), ("csg3d", "ply"), ("csg3d", "scad"),
                                         ("shapeassembly", "ply")])
def test_export_writes_what_infer_writes(domain, fmt, tmp_path):
    d = get_domain(domain)
    ids = d.sample(1, np.random.default_rng(1))[0]
    (written,) = [p for p in d.export_files(ids, tmp_path / "infer") if p.suffix == f".{fmt}"]
    assert main(["export", domain, d.format(ids), "--format", fmt, "-o", str(tmp_path / f"export.{fmt}")]) == 0
    assert (tmp_path / f"export.{fmt}").read_bytes() == written.read_bytes()
