"""Shipping never loses the one backup, whenever the process dies (issue 53, reproductions 3 and 11): a ship is
killed at every rename it makes (simulated: the rename raises a BaseException that nothing catches, as a
kill -9 leaves the files), and after each kill the domain's model is a complete pair that verifies (the old
one, or the new one through its pending sidecar), ``previous/`` is a valid pair, and the next ship settles
what the killed one left. A damaged pair never replaces the backup. ``plad models`` lists damaged shipped
files with what is wrong and a pretrained index entry without a checkpoint in one line, never a traceback."""
from __future__ import annotations

import contextlib
import json
import os
import shutil

import pytest

import plad.shipped as shipped
from plad.shipped import (
    CHECKPOINT,
    PRETRAINED_INDEX,
    PREVIOUS,
    SIDECAR,
    pretrained_model,
    ship,
    ship_pretrained,
    shipped_dir,
    shipped_model,
)


class Killed(BaseException):
    """What a kill -9 leaves: the rename did not happen and nothing after it ran."""


@pytest.fixture
def quick(monkeypatch):
    """Ships without the data files' checksums (the provenance is not what these tests are about)."""
    monkeypatch.setattr(shipped, "_provenance", lambda *a: {"git": {"revision": None, "dirty": None}})


@pytest.fixture
def dest(tmp_path):
    (tmp_path / "params.yaml").write_text("{}\n")    # the layout root's params (--root tmp_path)
    folder = tmp_path / "shipped"
    shutil.copytree(shipped_dir() / "csg2d", folder / "csg2d", ignore=shutil.ignore_patterns("pretrained.pt"))
    return folder


def metrics(path, mean: float):
    path.write_text(json.dumps({"domain": "csg2d", "method": "test", "metric": "chamfer", "higher_is_better": False,
                                "beam": 10, "test": {"mean": mean, "n": 3000}}))
    return path


@contextlib.contextmanager
def kill_at(k: int):
    """Within the block, the ``k``-th rename (1-based) dies."""
    real, seen = os.replace, []

    def replace(a, b):
        seen.append(b)
        if len(seen) == k:
            raise Killed(f"killed at rename {k}: {b}")
        return real(a, b)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(shipped.os, "replace", replace)
        yield


def valid_pair(folder):
    model = shipped_model("csg2d", folder.parent) if folder.name == "csg2d" else shipped._pair("csg2d", folder)
    assert model is not None and model.problem() is None, folder
    return model.test.get("mean")


def test_a_ship_killed_at_any_rename_loses_nothing(dest, tmp_path, tiny_checkpoint, quick):
    ckpt = tiny_checkpoint(tmp_path / "tiny.pt", "csg2d")
    ship("csg2d", ckpt, metrics(tmp_path / "m1.json", 0.1), dest=dest, root=tmp_path)   # previous/ exists now (0.1:
    # below any shipped 2D model's Chamfer)
    folder = dest / "csg2d"
    k = 1
    while True:
        before = valid_pair(folder)
        valid_pair(folder / PREVIOUS)
        try:
            with kill_at(k):
                ship("csg2d", ckpt, metrics(tmp_path / "m.json", 10.0 + k), dest=dest, root=tmp_path, force=True)
            break                                    # no rename left to kill at
        except Killed:
            pass
        now = valid_pair(folder)                     # a complete pair: the old model or the new one
        assert now in (before, 10.0 + k)
        shipped_model("csg2d", dest).verify()
        valid_pair(folder / PREVIOUS)                # the backup: a valid pair whenever the kill came
        ship("csg2d", ckpt, metrics(tmp_path / "m.json", 100.0 + k), dest=dest, root=tmp_path, force=True)
        assert valid_pair(folder) == 100.0 + k and valid_pair(folder / PREVIOUS) == now   # the backup is valid
        assert not [p.name for p in folder.rglob("*.new")]                             # the pending files settled
        k += 1
    assert k > 4   # the backup's two files and the model's two files were each killed around


def test_a_damaged_pair_never_replaces_the_backup(dest, tmp_path, tiny_checkpoint, quick, capsys):
    from plad.serve.cli import main

    ckpt = tiny_checkpoint(tmp_path / "tiny.pt", "csg2d")
    ship("csg2d", ckpt, metrics(tmp_path / "m.json", 0.1), dest=dest, root=tmp_path)   # better than the shipped one
    folder = dest / "csg2d"
    backup = {p.name: p.read_bytes() for p in (folder / PREVIOUS).iterdir()}
    # what a kill between the two files left in an older version: a sidecar naming another checkpoint
    (folder / SIDECAR).write_bytes((folder / PREVIOUS / SIDECAR).read_bytes())
    with pytest.raises(shipped.ShipError, match="differs from its sidecar"):
        shipped_model("csg2d", dest).verify()
    assert main(["models", "ship", "csg2d", str(ckpt), "--metrics", str(metrics(tmp_path / "m.json", 9.0)),
                 "--dest", str(dest), "--root", str(tmp_path), "--force"]) == 0
    err = capsys.readouterr().err
    assert "plad: note: the model replaced was not kept in" in err and "still holds the one before" in err
    assert {p.name: p.read_bytes() for p in (folder / PREVIOUS).iterdir()} == backup
    assert valid_pair(folder) == 9.0


def test_a_pretrained_ship_killed_at_any_rename_keeps_a_network_that_verifies(tmp_path):
    source = shipped_dir() / "csg3d" / "pretrained.pt"
    base = tmp_path / "dest"
    ship_pretrained("csg3d", source, dest=base)
    copy = tmp_path / "again.pt"
    shutil.copy(source, copy)
    for k in range(1, 6):
        try:
            with kill_at(k):
                ship_pretrained("csg3d", copy, dest=base)
        except Killed:
            pass
        model = pretrained_model("csg3d", base)
        model.verify()                               # the old network or the new one, never a mismatch
        ship_pretrained("csg3d", copy, dest=base)
        assert not list(base.rglob("*.new"))


def test_models_lists_damaged_files_and_a_damaged_index_in_one_line_each(tmp_path, monkeypatch, capsys):
    from plad.serve.cli import main

    base = tmp_path / "shipped"
    shutil.copytree(shipped_dir() / "csg2d", base / "csg2d", ignore=shutil.ignore_patterns("pretrained.pt"))
    shutil.copytree(shipped_dir() / "csg3d", base / "csg3d")
    index = json.loads((shipped_dir() / PRETRAINED_INDEX).read_text())
    index["domains"] = {"csg3d": index["domains"]["csg3d"], "csg2d": {"method": "sp"}}   # no checkpoint
    (base / PRETRAINED_INDEX).write_text(json.dumps(index))
    with open(base / "csg2d" / CHECKPOINT, "ab") as fh:
        fh.write(b"x")
    monkeypatch.setenv("PLAD_SHIPPED_DIR", str(base))
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["models"]) == 1
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "csg3d          pretrained" in out       # the others are listed
    assert f"provenance: DAMAGED: {base / 'csg2d' / CHECKPOINT}: sha256" in out
    errors = [line for line in err.splitlines() if line.startswith("plad: error:")]
    assert f"plad: error: {base / PRETRAINED_INDEX}: the entry of 'csg2d' has no checkpoint file and sha256 (a " \
           "damaged index)" in errors
    assert any("differs from its sidecar" in line for line in errors)
