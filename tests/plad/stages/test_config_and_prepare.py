"""params.yaml loading (typed, strict) and the ``prepare`` stage."""
import json

import numpy as np
import pytest

from plad.config import ConfigError, load_params, section
from plad.data.datasets.cad import load_cad
from plad.data.files import load_prepared
from plad.layout import Layout
from plad.learn.pretrain import PretrainConfig
from plad.stages.prepare import PrepareConfig, main, prepare
from tests.conftest import REPO_ROOT

REPO = REPO_ROOT


def test_repository_params_load():
    params = load_params(REPO / "params.yaml")
    cfg = section(params, "prepare", PrepareConfig)
    assert cfg.domains == params["domains"] and cfg.limit == {}


def test_unknown_keys_and_wrong_types_are_errors(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text("prepare:\n  data_dri: /x\n")
    with pytest.raises(ConfigError, match="unknown key.*data_dri.*allowed"):
        section(load_params(p), "prepare", PrepareConfig, source=str(p))
    p.write_text("domains: csg2d\nprepare: {}\n")
    with pytest.raises(ConfigError, match="prepare.domains"):
        section(load_params(p), "prepare", PrepareConfig)
    p.write_text("prepare: [\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_params(p)
    with pytest.raises(ConfigError, match="no such params file"):
        load_params(tmp_path / "missing.yaml")
    p.write_text("pretrian:\n  domain: csg2d\n")
    with pytest.raises(ConfigError, match="unknown section.*pretrian"):
        load_params(p)
    p.write_text("domains: [csg2d]\n")
    with pytest.raises(ConfigError, match="section 'prepare' is missing"):
        section(load_params(p), "prepare", PrepareConfig, source=str(p))
    p.write_text("pretrain:\n  base:\n    model:\n      d_modle: 3\n  csg2d: {}\n")
    with pytest.raises(ConfigError, match="d_modle.*pretrain.csg2d.model"):
        section(load_params(p), "pretrain.csg2d", PretrainConfig)


def test_prepare_writes_packed_splits_and_summary(tmp_path, datasets_dir):
    layout = Layout(tmp_path)
    summary = prepare(PrepareConfig(domains=["csg2d"], data_dir=str(datasets_dir)), layout)["domains"]["csg2d"]
    assert summary["train_count"] == 10000 and summary["test_count"] == 3000
    assert json.loads(layout.prepared_summary("csg2d").read_text()) == summary
    test = load_prepared(layout.prepared("csg2d"), "test")
    assert np.array_equal(test, load_cad(datasets_dir, "test"))
    assert not list(layout.prepared_dir.glob(".*.tmp"))  # no temporary files left


def test_prepare_main_reports_errors_in_one_line(tmp_path, capsys):
    p = tmp_path / "params.yaml"
    p.write_text(f"domains: [csg2d]\nprepare:\n  data_dir: {tmp_path}\n")
    assert main(["--params", str(p), "--root", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not found" in err
    p.write_text("prepare:\n  colour: red\n")
    assert main(["--params", str(p)]) == 1
    assert "unknown key" in capsys.readouterr().err
