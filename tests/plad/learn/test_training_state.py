"""One check of a training state before any training continues from it or any command ships it (issue 53,
reproductions 1 and 10): plad.learn.state.check_training_state refuses, in one line naming what is wrong,
damaged weights, Adam moments, schedules, RNG states, loop states, histories and provenance, wherever they come
from: ``pretrain.init`` (refused before anything trains), a run's own ``last.pt`` (never resumed), and
``plad models ship-pretrained`` (never shipped). The states the pretraining writes, and the shipped ones, pass.
"""
from __future__ import annotations

import copy
import math
import shutil

import numpy as np
import pytest
import torch

from plad.config import ConfigError
from plad.layout import LAST, Layout
from plad.learn.pretrain import pretrain, read_init
from plad.learn.state import check_training_state
from plad.model.checkpoint import CheckpointError, read_checkpoint
from plad.model.network import Architecture, ModelConfig
from tests.tiny import ARCHITECTURE, tiny_pretrain_config, tiny_pretrained_root

config = tiny_pretrain_config


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A layout root with 200 synthetic 2D programs and a one-epoch tiny pretraining."""
    return tiny_pretrained_root(tmp_path_factory.mktemp("trained"))


def _moments(p, key, value):
    for s in p["optimizer"]["state"].values():
        s[key] = s[key] * value


def _set(path, value):
    def damage(p):
        node = p
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return damage


DAMAGES = {
    # reproduction 1: NaN Adam moments
    "NaN exp_avg": (lambda p: _moments(p, "exp_avg", float("nan")), "exp_avg of parameter 0 holds NaN"),
    "inf exp_avg_sq": (lambda p: _moments(p, "exp_avg_sq", float("inf")), "exp_avg_sq of parameter 0 holds NaN"),
    "negative exp_avg_sq": (lambda p: _moments(p, "exp_avg_sq", -1.0), "negative values"),
    "moment shape": (lambda p: p["optimizer"]["state"][3].update(exp_avg=torch.zeros(7)), "is (7,), the parameter"),
    "shifted ids": (lambda p: p["optimizer"]["param_groups"][0].update(
        params=[i + 1 for i in p["optimizer"]["param_groups"][0]["params"]]), "parameter ids are not 0.."),
    "NaN lr": (lambda p: p["optimizer"]["param_groups"][0].update(lr=float("nan")), "learning rate is nan"),
    "NaN step": (lambda p: p["optimizer"]["state"][0].update(step=torch.tensor(float("nan"))), "optimizer step"),
    "optimizer text": (_set(["optimizer"], "x"), "not Adam's of one parameter group"),
    "state of a 99th parameter": (lambda p: p["optimizer"]["state"].update({99: p["optimizer"]["state"][0]}),
                                  "state for parameter 99"),
    # the learning-rate schedule (garbage accepted with continue_lr: resume before)
    "garbage scheduler": (_set(["scheduler"], {"mode": "min", "best": "garbage"}), "schedule's best is 'garbage'"),
    "scheduler mode": (_set(["scheduler", "mode"], "sideways"), "schedule's mode"),
    "bad epochs": (_set(["scheduler", "num_bad_epochs"], -3), "num_bad_epochs is -3"),
    "scheduler text": (_set(["scheduler"], 5), "schedule's state is not a mapping"),
    # random generators
    "torch rng": (_set(["rng", "torch"], torch.zeros(3, dtype=torch.uint8)), "random generators' state"),
    "numpy rng": (_set(["rng", "numpy"], ("MT19937", torch.zeros(3), 0, 0, 0.0)), "random generators' state"),
    "python rng": (_set(["rng", "python"], "x"), "random generators' state"),
    "no rng": (lambda p: p.pop("rng"), "no 'rng' entry"),
    # the loop state and its history (loop.unit=-5 was accepted silently before)
    "negative unit": (_set(["loop", "unit"], -5), "loop.unit = -5"),
    "segment after unit": (_set(["loop", "segment_unit"], 9), "loop.segment_unit = 9"),
    "NaN best": (_set(["loop", "best"], float("nan")), "loop.best = nan"),
    "seconds text": (_set(["loop", "seconds"], "x"), "loop.seconds = 'x'"),
    "history text": (_set(["loop", "history"], "x"), "loop.history is not a list"),
    "history row text": (lambda p: p["loop"]["history"][0].update(val_loss="x"), "holds 'val_loss' = 'x'"),
    "history ahead": (lambda p: p["loop"]["history"][0].update(unit=5), "loop.history row 0"),
    "no loop": (lambda p: p.pop("loop"), "no loop state"),
    # provenance (11 different tracebacks before, e.g. this one)
    "provenance text": (_set(["provenance"], {"segments": "x", "totals": {}}), "provenance.segments is not a list"),
    "segment epochs": (lambda p: p["provenance"]["segments"][0].update(epochs=[2, 5]), "covers epochs [2, 5]"),
    "segment steps": (lambda p: p["provenance"]["segments"][0].update(steps=-1), "steps = -1"),
    "totals": (lambda p: p["provenance"]["totals"].update(epochs=99), "are not the totals of its segments"),
    # weights
    "NaN weight": (lambda p: next(iter(p["state_dict"].values())).fill_(float("nan")), "holds NaN or infinite"),
    "huge weight": (lambda p: next(iter(p["state_dict"].values())).fill_(1e30), "a diverged or damaged network"),
    "weight shape": (lambda p: p["state_dict"].update({next(iter(p["state_dict"])): torch.zeros(2)}),
                     "its config needs"),
}


def _damaged(trained, damage):
    payload = copy.deepcopy(read_checkpoint(trained / "runs/pretrain/csg2d" / LAST))
    damage(payload)
    return payload


def test_the_written_state_and_the_shipped_ones_pass(trained):
    check_training_state("last.pt", read_checkpoint(trained / "runs/pretrain/csg2d" / LAST))
    from plad.shipped import list_pretrained

    for model in list_pretrained():
        check_training_state(model.checkpoint, read_checkpoint(model.checkpoint))


@pytest.mark.parametrize("case", list(DAMAGES))
def test_each_damage_is_refused_in_one_line_before_training(trained, tmp_path, case):
    damage, phrase = DAMAGES[case]
    path = tmp_path / "init.pt"
    torch.save(_damaged(trained, damage), path)
    with pytest.raises(CheckpointError) as err:
        check_training_state(path, read_checkpoint(path))
    line = str(err.value)
    assert phrase in line and "\n" not in line and line.startswith(f"{path}:"), line
    from plad.domains import get_domain

    with pytest.raises(ConfigError) as err:   # pretrain.init: one line naming the key, before anything trains
        read_init(path, config(1), ModelConfig.for_domain(Architecture(**ARCHITECTURE), get_domain("csg2d")))
    assert str(err.value).startswith(f"pretrain.csg2d.init: {path}") and "\n" not in str(err.value)


def test_random_non_finite_values_anywhere_in_adam_are_refused(trained, tmp_path):
    rng = np.random.default_rng(53)
    for _ in range(6):
        payload = _damaged(trained, lambda p: None)
        state = payload["optimizer"]["state"]
        pid = int(rng.choice(list(state)))
        key = str(rng.choice(["exp_avg", "exp_avg_sq"]))
        flat = state[pid][key].view(-1)
        flat[int(rng.integers(len(flat)))] = float(rng.choice([math.nan, math.inf, -math.inf]))
        with pytest.raises(CheckpointError, match=f"{key} of parameter {pid} holds NaN or infinite"):
            check_training_state("x.pt", payload)


def test_nan_moments_are_never_trained_from_resumed_or_shipped(trained, tmp_path):
    """Reproduction 1: the init is refused before training (no run folder written), a run's own damaged last.pt
    is never resumed, and ship-pretrained refuses it."""
    from plad.shipped import ShipError, ship_pretrained

    bad = tmp_path / "nan.pt"
    torch.save(_damaged(trained, DAMAGES["NaN exp_avg"][0]), bad)
    root = tmp_path / "root"
    shutil.copytree(trained / "data", root / "data")
    with pytest.raises(ConfigError, match="exp_avg of parameter 0 holds NaN"):
        pretrain(config(1, init=str(bad)), Layout(root))
    assert not (root / "runs/pretrain/csg2d" / LAST).exists()
    with pytest.raises(ShipError, match="exp_avg of parameter 0 holds NaN"):
        ship_pretrained("csg2d", bad, dest=tmp_path / "dest")
    assert not (tmp_path / "dest" / "csg2d" / "pretrained.pt").exists()

    resumed = tmp_path / "resumed"
    shutil.copytree(trained, resumed)
    torch.save(_damaged(trained, DAMAGES["NaN exp_avg"][0]), resumed / "runs/pretrain/csg2d" / LAST)
    with pytest.raises(CheckpointError, match="exp_avg of parameter 0 holds NaN"):
        pretrain(config(2), Layout(resumed))


def test_an_empty_set_value_and_a_fresh_run_of_no_epochs_are_one_line(trained, tmp_path, capsys):
    from plad.stages.pretrain import main

    params = tmp_path / "params.yaml"
    from tests.tiny import tiny_pretrain_params

    tiny_pretrain_params(params)
    root = tmp_path / "root"
    shutil.copytree(trained / "data", root / "data")
    base = ["--params", str(params), "--section", "pretrain.csg2d", "--root", str(root)]
    assert main([*base, "--set", "init="]) == 1
    assert capsys.readouterr().err.strip() == "pretrain: error: --set 'init=': no value; write init=null for none"
    assert main([*base, "--set", "init=null", "--set", "train.max_epochs=0"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("pretrain: error: pretrain.csg2d.train.max_epochs = 0 trains nothing") and "\n" not in err
    assert not (root / "runs").exists()              # refused before any MLflow run or file
