"""A method's own ``max_minutes`` (rows beyond the paper) replaces the stage's budget; the summary records it."""
from __future__ import annotations

import json

import pytest

from plad.layout import Layout
from plad.learn.methods import MethodConfig
from plad.learn.rounds import RoundsConfig
from plad.learn.train import TrainConfig
from plad.stages.finetune import FinetuneStageConfig, finetune_stage
from tests.tiny import csg2d_inputs, tiny_checkpoint

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def layout(tmp_path_factory, datasets_dir):
    root = csg2d_inputs(tmp_path_factory.mktemp("budget"), datasets_dir)
    tiny_checkpoint(Layout(root).model("csg2d", "sp"), "csg2d")
    return Layout(root)


@pytest.fixture
def swap_pretrained(layout):
    """``swap_pretrained()`` replaces the module's pretrained model (the tiny one, seed 0) by another (seed 5);
    the module's model is put back after the test, whether it passed or failed."""
    sp = layout.model("csg2d", "sp")
    original = sp.read_bytes()
    yield lambda: tiny_checkpoint(sp, "csg2d", seed=5)
    sp.write_bytes(original)


def config(key: str, stage_minutes, method_minutes) -> FinetuneStageConfig:
    plad = RoundsConfig(infer_beam=1, infer_batch=8, val_beam_epoch=1, val_beam_round=1, max_rounds=3,
                        train=TrainConfig(batch_size=4, steps_per_epoch=2, max_epochs=1))
    return FinetuneStageConfig(domain="csg2d", key=key, device="cpu", threads=1, train_limit=8, val_limit=4,
                               max_minutes=stage_minutes, plad=plad,
                               methods={key: MethodConfig(method="st", max_minutes=method_minutes)})


def test_the_method_budget_replaces_the_stage_budget(layout):
    short = finetune_stage(config("short", stage_minutes=None, method_minutes=1e-6), layout)
    assert short["max_minutes"] == 1e-6 and short["stopped"] == "budget" and short["units"] <= 1
    free = finetune_stage(config("free", stage_minutes=1e-6, method_minutes=None), layout)
    assert free["max_minutes"] == 1e-6 and free["stopped"] == "budget"
    long = finetune_stage(config("long", stage_minutes=1e-6, method_minutes=60), layout)
    assert long["max_minutes"] == 60 and long["stopped"] != "budget" and long["units"] == 3
    assert json.loads(layout.finetune_summary("csg2d", "long").read_text())["max_minutes"] == 60


def test_a_run_folder_started_from_another_model_is_started_over_not_resumed(layout, swap_pretrained, capsys):
    cfg = config("origin", stage_minutes=None, method_minutes=None)
    cfg.plad.max_rounds = 1
    first = finetune_stage(cfg, layout)
    assert first["units"] == 1
    cfg.plad.max_rounds = 2     # more rounds: the same run continues
    assert finetune_stage(cfg, layout)["units"] == 2
    assert "resuming from round 2" in capsys.readouterr().err
    swap_pretrained()                             # another pretrained model: the old rounds are void
    again = finetune_stage(cfg, layout)
    err = capsys.readouterr().err
    assert "not resuming" in err and "model_network_sha256 changed" in err and "resuming from" not in err
    assert again["units"] == 2
