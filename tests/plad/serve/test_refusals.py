"""Refused before any work, in one line (issue 30): a beam outside 1..MAX_BEAM, and a model URI when no MLflow
store is configured (a look-up creates no ./mlflow.db and prints none of MLflow's lines)."""
from __future__ import annotations

import numpy as np
import pytest

from plad.serve.cli import main


@pytest.fixture
def shape(tmp_path):
    grid = np.zeros((64, 64), bool)
    grid[20:40, 16:48] = True
    np.save(tmp_path / "in.npy", grid)
    return tmp_path / "in.npy"


@pytest.mark.parametrize("beam", ["0", "101", "100000", "1000000000"])
def test_a_beam_outside_1_to_max_beam(shape, tmp_path, capsys, beam):
    assert main(["infer", "csg2d", str(shape), "--beam", beam, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err == f"plad: error: --beam {beam}: a beam width is an integer from 1 to 100 (MAX_BEAM), got {beam}\n"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("uri", ["runs:/0123456789abcdef/model", "models:/plad-csg2d@champion"])
def test_a_model_uri_without_a_store_creates_nothing(shape, tmp_path, capsys, monkeypatch, uri):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["infer", "csg2d", str(shape), "--model", uri, "--out", str(tmp_path / "out")]) == 1
    captured = capsys.readouterr()
    assert captured.err == (f"plad: error: {uri}: no MLflow store to look it up in ($MLFLOW_TRACKING_URI is unset "
                            f"and there is no ./mlflow.db); a look-up creates none\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.npy"]
