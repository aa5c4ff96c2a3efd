"""Shipped pretrained networks: shipping a pretraining's state, listing it, continuing it, refusing damage."""
from __future__ import annotations

import json
import shutil

import pytest
import torch

from plad.layout import LAST, Layout
from plad.learn.pretrain import PretrainConfig, pretrain
from plad.model.checkpoint import read_checkpoint
from plad.shipped import (
    PRETRAINED,
    PRETRAINED_INDEX,
    ShipError,
    list_pretrained,
    pretrained_checkpoint,
    sha256_file,
    ship_pretrained,
)
from tests.tiny import tiny_pretrain_config, tiny_pretrained_root

config = tiny_pretrain_config


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A layout root with 200 synthetic 2D programs and a one-epoch pretraining."""
    return tiny_pretrained_root(tmp_path_factory.mktemp("trained"))


def test_ship_copies_the_state_and_indexes_its_provenance(trained, tmp_path):
    last = trained / "runs/pretrain/csg2d" / LAST
    model = ship_pretrained("csg2d", last, dest=tmp_path)
    assert model.checkpoint == tmp_path / "csg2d" / PRETRAINED
    assert sha256_file(model.checkpoint) == sha256_file(last)    # the whole state, as it was
    index = json.loads((tmp_path / PRETRAINED_INDEX).read_text())
    entry = index["domains"]["csg2d"]
    assert entry["checkpoint"]["sha256"] == sha256_file(last) and entry["method"] == "sp"
    assert entry["provenance"]["totals"]["epochs"] == 1 and entry["provenance"]["totals"]["shapes_seen"] == 32
    assert [m.domain for m in list_pretrained(tmp_path)] == ["csg2d"]
    assert pretrained_checkpoint("csg2d", tmp_path) == model.checkpoint


def test_a_damaged_or_missing_pretrained_network_is_refused_in_one_line(trained, tmp_path):
    ship_pretrained("csg2d", trained / "runs/pretrain/csg2d" / LAST, dest=tmp_path)
    with open(tmp_path / "csg2d" / PRETRAINED, "ab") as fh:
        fh.write(b"x")
    with pytest.raises(ShipError, match="differs from"):
        pretrained_checkpoint("csg2d", tmp_path)
    with pytest.raises(ShipError, match="no pretrained csg3d network is shipped"):
        pretrained_checkpoint("csg3d", tmp_path)


def test_only_a_training_state_with_provenance_ships(trained, tmp_path):
    payload = read_checkpoint(trained / "runs/pretrain/csg2d" / LAST)
    del payload["provenance"]
    torch.save(payload, tmp_path / "old.pt")
    with pytest.raises(ShipError, match="provenance segments"):
        ship_pretrained("csg2d", tmp_path / "old.pt", dest=tmp_path / "dest")
    with pytest.raises(ShipError, match="not a csg3d one"):
        ship_pretrained("csg3d", trained / "runs/pretrain/csg2d" / LAST, dest=tmp_path / "dest")


def test_init_shipped_continues_the_shipped_network_and_models_lists_it(trained, tmp_path, monkeypatch, capsys):
    from plad.serve.cli import main
    from plad.serve.resolve import resolve
    from plad.stages.pretrain import resolve_init

    dest = tmp_path / "shipped"
    assert main(["models", "ship-pretrained", "csg2d", str(trained / "runs/pretrain/csg2d" / LAST),
                 "--dest", str(dest)]) == 0
    monkeypatch.setenv("PLAD_SHIPPED_DIR", str(dest))
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["models"]) == 0
    listed = capsys.readouterr().out
    assert "pretrained" in listed and "1 epochs, 0.00 M shapes, 0.0 h of training (0.0 CPU h)" in listed

    root = tmp_path / "again"
    shutil.copytree(trained / "data", root / "data")
    cfg = config(1, init="shipped")
    init = resolve_init(cfg, Layout(root))
    assert init == dest / "csg2d" / PRETRAINED
    pretrain(cfg, Layout(root), init_path=init)
    segs = read_checkpoint(root / "runs/pretrain/csg2d" / LAST)["provenance"]["segments"]
    assert [s["epochs"] for s in segs] == [[1, 1], [2, 2]] and segs[1]["init"]["file"] == PRETRAINED
    # with no fine-tuned network shipped, `plad infer` uses the pretrained one
    choice = resolve("csg2d")
    assert choice.kind == "shipped" and choice.path == dest / "csg2d" / PRETRAINED


def test_the_cpu_profile_continues_the_shipped_3d_networks_and_they_verify():
    """params.yaml (the cpu profile) resolves init to the shipped checkpoints, which match their index and
    hold the training state and provenance a continued pretraining needs."""
    from plad.config import build, load_params
    from plad.domains import get_domain
    from plad.learn.pretrain import read_init
    from plad.model.network import ModelConfig
    from plad.stages.pretrain import resolve_init
    from tests.conftest import REPO_ROOT

    params = load_params(REPO_ROOT / "params.yaml")
    assert params["profile"] == "cpu"
    for domain in ("csg3d", "shapeassembly"):
        cfg = build(PretrainConfig, params["pretrain"][domain], f"pretrain.{domain}")
        assert cfg.init == "shipped"
        path = resolve_init(cfg, Layout(REPO_ROOT))
        assert path == REPO_ROOT / "plad/shipped" / domain / PRETRAINED
        payload = read_init(path, cfg, ModelConfig.for_domain(cfg.model, get_domain(domain)))
        totals = payload["provenance"]["totals"]
        assert totals["epochs"] == payload["loop"]["unit"] and totals["shapes_seen"] > 0
        assert path.stat().st_size < 20 * 2**20
