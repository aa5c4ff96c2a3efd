"""The prepared GPU command (plad.tools.gpu_segment): its programs, and a CPU dry run as on a lent machine."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from plad.fsutil import sha256_file
from plad.tools.gpu_segment import next_seed, sample_programs

REPO = Path(__file__).resolve().parents[3]
PREPARED = REPO / "data" / "prepared" / "shapeassembly.npz"

#: a lent GPU machine has none of these (docs/gpu.md): the dry run must not import them
ABSENT_THERE = ("mlflow", "dvc", "prefect", "open3d", "dask")

BLOCKER = """
import importlib.abc, sys
class _Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {names!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (absent on a lent GPU machine)")
        return None
sys.meta_path.insert(0, _Absent())
"""


def test_the_programs_do_not_depend_on_the_number_of_processes():
    counts = {"val": 30, "train": 70}
    one = sample_programs("csg2d", "paper", 7, counts, chunk=20, procs=1)
    two = sample_programs("csg2d", "paper", 7, counts, chunk=20, procs=2)
    assert sorted(one) == ["train", "train_complexity", "val", "val_complexity"]
    assert one["train"].shape == (70, two["train"].shape[1]) and one["val"].shape[0] == 30
    for key in one:
        np.testing.assert_array_equal(one[key], two[key])
    other = sample_programs("csg2d", "paper", 8, counts, chunk=20, procs=1)
    assert not np.array_equal(one["train"], other["train"])   # another seed, other programs
    assert not np.array_equal(one["train"][:30], one["val"])  # the splits draw from independent streams


def test_the_default_seed_is_one_the_shipped_segments_never_used():
    # seeds 2 and 3 (ShapeAssembly), 2-4 (3D CSG), 0-4 (2D) in plad/shipped/pretrained.json; shipping a
    # segment of a new seed moves these
    assert {d: next_seed(d) for d in ("csg2d", "csg3d", "shapeassembly")} == {"csg2d": 5, "csg3d": 5,
                                                                               "shapeassembly": 4}


@pytest.mark.integration
def test_a_dry_run_on_the_cpu_without_mlflow_dvc_or_prefect(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(BLOCKER.format(names=set(ABSENT_THERE)))
    shipped = REPO / "plad" / "shipped" / "shapeassembly" / "pretrained.pt"
    before = sha256_file(shipped)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(REPO)]), "OMP_NUM_THREADS": "1"}
    out, work = tmp_path / "out", tmp_path / "work"
    cmd = [sys.executable, "-m", "plad.tools.gpu_segment", "shapeassembly", "--out", str(out), "--work", str(work),
           "--params", str(REPO / "params.yaml"), "--profile", "cpu", "--device", "cpu", "--minutes", "0.05",
           "--programs", "120", "--val-programs", "40", "--chunk", "40", "--procs", "2", "--batch-size", "8",
           "--loader-workers", "1", "--threads", "1", "--set", "val_metric_shapes=4", "--set", "gap_programs=8",
           "--set", "train.steps_per_epoch=3",
           # a clean clone has no prepared shapes (the prepare stage makes them); the lent machine gets them by carry
           *(["--set", "real_val_shapes=4"] if PREPARED.exists() else ["--no-real-val"])]
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "synthesized 120 + 40 programs (seed 4) in" in done.stdout
    assert sorted(p.name for p in out.iterdir()) == ["history.csv", "last.pt", "provenance.json", "summary.json",
                                                    "synthetic.json"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["domain"] == "shapeassembly" and summary["stopped"] == "budget" and summary["units"] > 125
    segment = json.loads((out / "provenance.json").read_text())["segments"][-1]
    assert segment["device"] == "cpu" and segment["epochs"][0] == 126           # a new segment after the shipped 125
    assert segment["synthetic"] | {"checksum": None} == {"file": "shapeassembly.npz", "sampler": "paper", "seed": 4,
                                                         "train_programs": 120, "checksum": None}
    assert segment["init"]["sha256"] == before
    assert json.loads((out / "synthetic.json").read_text())["made_by"] == "plad.tools.gpu_segment"
    assert sha256_file(shipped) == before                                    # the shipped network is left alone
    # the last line is the summary's numbers, one JSON object
    assert json.loads(done.stdout.strip().splitlines()[-1])["stopped"] == "budget"


def test_real_validation_shapes_that_did_not_travel_are_a_one_line_error_before_any_work(tmp_path, capsys):
    from plad.tools.gpu_segment import main

    (tmp_path / "params.yaml").write_text((REPO / "params.yaml").read_text())
    (tmp_path / "profiles").symlink_to(REPO / "profiles")
    status = main(["shapeassembly", "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"),
                   "--params", str(tmp_path / "params.yaml")])
    out, err = capsys.readouterr()
    assert status == 2 and out == ""
    assert err == (f"gpu_segment: error: {tmp_path}/data/prepared/shapeassembly.npz: the real validation shapes are "
                   "not there (carry data/prepared/shapeassembly.npz to the lent machine, or --no-real-val)\n")
    assert not (tmp_path / "work" / "data" / "synthetic").exists()      # no programs sampled first
