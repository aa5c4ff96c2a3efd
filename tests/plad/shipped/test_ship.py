"""`plad models ship` replaces a shipped model only with a better one (by its test metric, in the metric's
direction, on the same test) unless --force, and keeps the one it replaces (issue 30)."""
from __future__ import annotations

import json
import shutil

import pytest

from plad.serve.cli import main
from plad.shipped import CHECKPOINT, PREVIOUS, SIDECAR, shipped_dir, shipped_model
from tests.conftest import REPO_ROOT


@pytest.fixture
def dest(tmp_path):
    """A folder of shipped models holding a copy of the real shipped 2D model (its test Chamfer on n 3000)."""
    folder = tmp_path / "shipped"
    shutil.copytree(shipped_dir() / "csg2d", folder / "csg2d")
    return folder


def metrics(path, mean: float, n: int = 3000, beam: int = 10):
    path.write_text(json.dumps({"domain": "csg2d", "method": "test", "metric": "chamfer", "higher_is_better": False,
                                "beam": beam, "test": {"mean": mean, "n": n}}))
    return path


def files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def ship(dest, checkpoint, metrics_path, *extra, data_dir=None):
    return main(["models", "ship", "csg2d", str(checkpoint), "--metrics", str(metrics_path), "--dest", str(dest),
                 "--root", str(REPO_ROOT), *(["--data-dir", str(data_dir)] if data_dir else []), *extra])


@pytest.mark.parametrize("mean, n, phrase", [
    # {shipped}: the shipped model's test mean as its sidecar records it (it changes when a better one ships)
    (9.99, 3000, "this one's chamfer 9.99 (n 3000, beam 10) is not better than the shipped csg2d model's test "
                 "chamfer {shipped} (n 3000, beam 10)"),
    (0.5, 8, "are not measured alike"),
])
def test_a_worse_or_incomparable_model_is_not_shipped(dest, tmp_path, capsys, tiny_checkpoint, mean, n, phrase):
    ckpt = tiny_checkpoint(tmp_path / "tiny.pt", "csg2d")
    before = files(dest)
    assert ship(dest, ckpt, metrics(tmp_path / "m.json", mean, n)) == 1
    err = capsys.readouterr().err
    phrase = phrase.format(shipped=shipped_model("csg2d", dest).test["mean"])
    assert err.count("\n") == 1 and phrase in err and "--force" in err
    assert files(dest) == before


def test_a_better_one_is_shipped_and_force_ships_a_worse_one_keeping_the_replaced(dest, tmp_path, capsys,
                                                                                  tiny_checkpoint, datasets_dir):
    ckpt = tiny_checkpoint(tmp_path / "tiny.pt", "csg2d")
    original = files(dest / "csg2d")
    better = round(shipped_model("csg2d", dest).test["mean"] - 0.01, 6)     # below the shipped one's Chamfer
    assert ship(dest, ckpt, metrics(tmp_path / "m.json", better), data_dir=datasets_dir) == 0
    assert shipped_model("csg2d", dest).test["mean"] == better
    kept = files(dest / "csg2d" / PREVIOUS)
    assert kept == {k: v for k, v in original.items() if k in (CHECKPOINT, SIDECAR)}   # the replaced model, as it was
    shipped_once = files(dest / "csg2d")
    assert ship(dest, ckpt, metrics(tmp_path / "m.json", 5.0), "--force", data_dir=datasets_dir) == 0
    assert shipped_model("csg2d", dest).test["mean"] == 5.0
    assert files(dest / "csg2d" / PREVIOUS) == {k: v for k, v in shipped_once.items() if k in (CHECKPOINT, SIDECAR)}
    capsys.readouterr()
