"""`plad infer` keeps every run's rows; bad inputs (oversized, NaN, wrong dimensions, empty) are refused at
the edge with one line, the good files of a folder still processed (issue 18)."""
from __future__ import annotations

import csv
import os
import re
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from plad.domains import get_domain
from plad.serve.cli import main
from tests.conftest import REPO_ROOT

REPO = REPO_ROOT


def _tiny(domain_name: str):
    from plad.model.network import ModelConfig, PLADNet

    d = get_domain(domain_name)
    torch.manual_seed(0)
    return PLADNet(ModelConfig(vocab_size=len(d.tokens), max_len=d.tokens.max_len, input_shape=d.shape,
                               enc_channels=(4, 8, 8, 8), d_model=32, n_layers=1, n_heads=2, dim_ff=32)).eval()


@pytest.fixture(scope="module")
def model2d(tmp_path_factory):
    from plad.model.checkpoint import save_checkpoint

    path = tmp_path_factory.mktemp("model") / "csg2d.pt"
    return save_checkpoint(path, _tiny("csg2d"), "csg2d", get_domain("csg2d").tokens.names)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def bomb_png(path: Path, side: int = 20000) -> Path:
    """A valid PNG header for a side x side 1-bit image (a few bytes on disk; 400 M pixels decoded)."""
    ihdr = struct.pack(">IIBBBBB", side, side, 1, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * (side // 8 + 1) * 4)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b""))
    return path


def good_png(path: Path, offset: int = 0) -> Path:
    from PIL import Image

    img = np.full((64, 64), 255, np.uint8)
    img[16 + offset:40 + offset, 20:44] = 0
    Image.fromarray(img).save(path)
    return path


def rows(csv_path: Path) -> list[dict]:
    with open(csv_path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_a_folder_with_a_bomb_and_nan_keeps_the_good_files(model2d, tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    bomb_png(folder / "huge.png")
    np.save(folder / "nan.npy", np.full((64, 64), np.nan))
    np.save(folder / "voxels.npy", np.ones((32, 32, 32), bool))    # a 3D grid is not a csg2d shape
    good_png(folder / "a.png")
    good_png(folder / "b.png", offset=4)
    out = tmp_path / "out"
    status = main(["infer", "csg2d", str(folder), "--model", str(model2d), "--beam", "2", "--no-refine",
                   "--out", str(out)])
    err = capsys.readouterr().err
    assert status == 2 and "Traceback" not in err
    assert "huge.png: the image has 400,000,000 pixels, more than the limit of 25,000,000 pixels" in err
    assert "nan.npy: the array holds NaN or infinite values" in err
    assert "voxels.npy: expected an array of shape (64, 64) or (N, 64, 64)" in err
    closing = err.strip().splitlines()[-1]
    (run,) = list(out.iterdir())
    assert re.fullmatch(rf"2 of 5 shapes inferred in \d+\.\d s; this run's rows: {re.escape(str(run))}/results.csv",
                        closing)
    by = {r["name"]: r["status"] for r in rows(run / "results.csv")}
    assert by == {"a": "ok", "b": "ok", "huge": "error", "nan": "error", "voxels": "error"}
    assert (run / "a.txt").is_file() and (run / "b.txt").is_file()


def test_score_refuses_oversized_nan_and_wrongly_shaped_inputs(tmp_path, capsys):
    target = tmp_path / "t.npy"
    grid = np.zeros((64, 64), bool)
    grid[10:30, 10:30] = True
    np.save(target, grid)
    np.save(tmp_path / "nan.npy", np.full((64, 64), np.nan))
    np.save(tmp_path / "inf.npy", np.where(grid, np.inf, 0.0))
    np.save(tmp_path / "vox.npy", np.ones((32, 32, 32), bool))
    cases = {bomb_png(tmp_path / "huge.png"): "more than the limit of 25,000,000 pixels",
             bomb_png(tmp_path / "big.png", 6000): "the image is 6000x6000 pixels, more than the limit",
             tmp_path / "nan.npy": "NaN or infinite", tmp_path / "inf.npy": "NaN or infinite",
             tmp_path / "vox.npy": "its dimensions do not match the domain"}
    for path, phrase in cases.items():
        for args in (["--pred", str(path), "--target", str(target)], ["--pred", str(target), "--target", str(path)]):
            assert main(["score", "csg2d", *args]) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and phrase in err and str(path) in err, err


@pytest.mark.parametrize("domain", ["csg2d", "csg3d", "shapeassembly"])
def test_an_empty_target_is_refused_in_every_domain(domain, tmp_path, capsys):
    """Empty vs empty scored 16.0 with chamfer but IoU 1.0: the one rule is that an empty target is refused."""
    shape = get_domain(domain).shape
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros(shape, bool))
    assert main(["score", domain, "--pred", str(empty), "--target", str(empty)]) == 2
    assert "an empty target is refused in every domain" in capsys.readouterr().err
    full = np.zeros(shape, bool)
    full[(slice(4, 12),) * len(shape)] = True
    np.save(tmp_path / "full.npy", full)
    # an empty prediction is allowed: scored by the domain's metric
    assert main(["score", domain, "--pred", str(empty), "--target", str(tmp_path / "full.npy")]) == 0
    if get_domain(domain).rewrite is not None:
        assert main(["search", domain, str(empty)]) == 2
        assert "an empty target is refused" in capsys.readouterr().err


def _infer_cmd(model, inputs, out):
    code = "import sys; from plad.serve.cli import main; sys.exit(main(sys.argv[1:]))"
    return [sys.executable, "-c", code, "infer", "csg2d", *map(str, inputs), "--model", str(model), "--beam", "2",
            "--no-refine", "--out", str(out)]


def test_two_concurrent_runs_into_one_out_keep_all_their_rows(model2d, tmp_path):
    out = tmp_path / "out"
    inputs = {}
    for run in ("x", "y"):
        folder = tmp_path / run
        folder.mkdir()
        inputs[run] = [good_png(folder / "same.png", 0), good_png(folder / f"{run}.png", 3)]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    procs = [subprocess.Popen(_infer_cmd(model2d, inputs[r], out), cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in ("x", "y")]
    results = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], results
    runs = sorted(p for p in out.iterdir())
    assert len(runs) == 2
    closings = {re.sub(r" in \d+\.\d s;", ";", err.strip().splitlines()[-1]) for _, err in results}
    assert closings == {f"2 of 2 shapes inferred; this run's rows: {r / 'results.csv'}" for r in runs}
    files = sorted(row["file"] for r in runs for row in rows(r / "results.csv"))
    assert files == sorted(str(p) for r in ("x", "y") for p in inputs[r])
    for r in runs:   # both runs' same-named outputs are kept
        assert (r / "same.txt").is_file()


def test_a_second_run_into_the_same_out_keeps_the_first(model2d, tmp_path, capsys):
    out = tmp_path / "out"
    a, b = good_png(tmp_path / "a.png"), good_png(tmp_path / "b.png", 2)
    assert main(["infer", "csg2d", str(a), "--model", str(model2d), "--beam", "2", "--no-refine", "--out",
                 str(out)]) == 0
    assert main(["infer", "csg2d", str(b), "--model", str(model2d), "--beam", "2", "--no-refine", "--out",
                 str(out)]) == 0
    runs = sorted(out.iterdir())
    assert len(runs) == 2
    assert sorted(row["name"] for r in runs for row in rows(r / "results.csv")) == ["a", "b"]
