"""Keeping a shipped taught network as the start of a longer teaching run (plad.tools.keep_taught)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from plad.shipped import ShipError, kept_checkpoint, shipped_dir
from plad.tools.keep_taught import keep


def _shipped_copy(folder: Path, domain: str) -> None:
    (folder / domain).mkdir(parents=True)
    for name in ("model.pt", "model.json"):
        shutil.copyfile(shipped_dir() / domain / name, folder / domain / name)


def test_keep_copies_the_shipped_model_and_indexes_it(tmp_path):
    _shipped_copy(tmp_path, "csg3d")
    entry = keep("csg3d", tmp_path, commit="abc1234")
    kept = tmp_path / "csg3d" / "taught.pt"
    assert kept.read_bytes() == (tmp_path / "csg3d" / "model.pt").read_bytes()
    info = json.loads((tmp_path / "csg3d" / "model.json").read_text())
    assert entry == {"file": "csg3d/taught.pt", "sha256": info["checkpoint"]["sha256"],
                     "from": info["checkpoint"]["shipped_from"], "shipped_as": "plad/shipped/csg3d/model.pt at abc1234",
                     "test": {k: info["metrics"][k] for k in ("metric", "beam", "mean", "n")}}
    # teach's init: taught finds it, verified
    assert kept_checkpoint("csg3d", "taught", tmp_path) == kept
    # another domain is added beside it; keeping again replaces its own entry only
    _shipped_copy(tmp_path, "shapeassembly")
    keep("shapeassembly", tmp_path, commit="def5678")
    index = json.loads((tmp_path / "taught.json").read_text())
    assert index["format"] == "plad-taught-1" and sorted(index["models"]) == ["csg3d", "shapeassembly"]
    assert index["models"]["csg3d"] == entry


def test_keep_refuses_what_is_not_a_shipped_taught_network(tmp_path):
    with pytest.raises(ShipError, match="no shipped model to keep"):
        keep("csg3d", tmp_path)
    _shipped_copy(tmp_path, "csg3d")
    sidecar = tmp_path / "csg3d" / "model.json"
    sidecar.write_text(json.dumps({**json.loads(sidecar.read_text()), "method": "lest_st_ws_search"}))
    with pytest.raises(ShipError, match="method 'lest_st_ws_search', not a taught network"):
        keep("csg3d", tmp_path)
    assert not (tmp_path / "csg3d" / "taught.pt").exists() and not (tmp_path / "taught.json").exists()
