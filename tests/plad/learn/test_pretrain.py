"""Pretraining that accumulates: a run continued from a checkpoint (``pretrain.init``) as a new segment.

Tiny 2D networks on 200 synthetic programs, one thread: a continued run trains exactly as the uninterrupted
run would have, its provenance segments add up, a restarted learning rate starts again, and checkpoints of
another network or domain are refused in one line.
"""
from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace

import pytest
import torch

from plad.config import ConfigError
from plad.layout import BEST, HISTORY, LAST, PROVENANCE, Layout
from plad.learn.curriculum import CurriculumConfig
from plad.learn.pretrain import PretrainConfig, pretrain
from plad.learn.train import TrainConfig
from plad.model.checkpoint import read_checkpoint
from plad.model.network import Architecture
from tests.tiny import ARCHITECTURE


@pytest.fixture(scope="module")
def programs(tmp_path_factory):
    """A layout root holding 200 synthetic 2D programs (copied into each run's own root)."""
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    root = tmp_path_factory.mktemp("programs")
    synthesize(SynthesizeConfig(domain="csg2d", train_programs=200, val_programs=20, seed=3), Layout(root))
    return root


def run_root(programs, tmp_path, name):
    root = tmp_path / name
    shutil.copytree(programs / "data", root / "data")
    return Layout(root)


def config(epochs, curriculum=False, **kw):
    train = TrainConfig(batch_size=8, steps_per_epoch=4, max_epochs=epochs, lr=1e-3, patience=100,
                        **kw.pop("train", {}))
    cur = CurriculumConfig(enabled=True, stages=[2, 4], stage_steps=4) if curriculum else CurriculumConfig()
    return PretrainConfig(domain="csg2d", device="cpu", threads=1, val_metric_shapes=4, gap_programs=4,
                          model=Architecture(**ARCHITECTURE), train=train, curriculum=cur, **kw)


@pytest.mark.parametrize("curriculum", [False, True], ids=["plain", "curriculum"])
def test_a_continued_pretraining_ends_with_the_weights_of_the_uninterrupted_run(programs, tmp_path, curriculum):
    whole, first, second = (run_root(programs, tmp_path, n) for n in ("whole", "first", "second"))
    pretrain(config(3, curriculum), whole)
    pretrain(config(2, curriculum), first)
    init = first.pretrain_dir("csg2d") / LAST
    pretrain(config(1, curriculum, init=str(init), continue_lr="resume"), second)

    a = read_checkpoint(whole.pretrain_dir("csg2d") / LAST)
    b = read_checkpoint(second.pretrain_dir("csg2d") / LAST)
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for k in a["state_dict"]:
        assert torch.equal(a["state_dict"][k], b["state_dict"][k]), k
    assert a["loop"]["unit"] == b["loop"]["unit"] == 3
    # the history continues: the first run's epochs, then the segment's, as in the uninterrupted run
    rows = lambda layout: list(csv.DictReader((layout.pretrain_dir("csg2d") / HISTORY).open()))  # noqa: E731
    assert [r["epoch"] for r in rows(second)] == ["1", "2", "3"]
    assert [r["train_loss"] for r in rows(second)] == [r["train_loss"] for r in rows(whole)]


def test_provenance_segments_add_up_and_travel_with_the_checkpoints(programs, tmp_path):
    first, second = run_root(programs, tmp_path, "first"), run_root(programs, tmp_path, "second")
    pretrain(config(2), first)
    pretrain(config(1, init=str(first.pretrain_dir("csg2d") / LAST)), second)
    out = second.pretrain_dir("csg2d")
    prov = read_checkpoint(out / LAST)["provenance"]
    segs, tot = prov["segments"], prov["totals"]
    assert [s["epochs"] for s in segs] == [[1, 2], [3, 3]]
    assert [s["steps"] for s in segs] == [8, 4] and [s["shapes_seen"] for s in segs] == [64, 32]
    assert tot["epochs"] == 3 and tot["steps"] == 12 and tot["shapes_seen"] == 96 and tot["segments"] == 2
    assert tot["train_seconds"] == pytest.approx(sum(s["train_seconds"] for s in segs), abs=0.11)
    assert tot["cpu_hours"] == pytest.approx(sum(s["cpu_hours"] for s in segs), abs=1e-3)
    assert tot["cpu_hours_complete"] is True
    assert all(s["threads"] == 1 and s["device"] == "cpu" and s["recorded"] for s in segs)
    assert segs[1]["init"]["file"] == LAST and segs[0]["init"] is None
    assert segs[1]["params"]["init"] == LAST   # the file's name, not this machine's absolute path
    assert segs[0]["synthetic"]["seed"] == 3 and segs[0]["synthetic"]["train_programs"] == 200
    assert "real_val_chamfer" not in segs[1]["end"] and "prefix_gap" in segs[1]["end"]
    # best.pt (the model) and provenance.json say the same
    assert read_checkpoint(out / BEST)["provenance"] == prov
    assert json.loads((out / PROVENANCE).read_text()) == json.loads(json.dumps(prov))


def test_a_checkpoint_without_segments_becomes_one_unrecorded_segment(programs, tmp_path):
    first, second = run_root(programs, tmp_path, "first"), run_root(programs, tmp_path, "second")
    pretrain(config(1), first)
    old = first.pretrain_dir("csg2d") / LAST
    payload = read_checkpoint(old)
    del payload["provenance"]
    torch.save(payload, old)
    pretrain(config(1, init=str(old)), second)
    segs = read_checkpoint(second.pretrain_dir("csg2d") / LAST)["provenance"]["segments"]
    assert segs[0]["recorded"] is False and segs[0]["epochs"] == [1, 1] and segs[0]["shapes_seen"] == 32
    assert segs[0]["cpu_hours"] is None
    tot = read_checkpoint(second.pretrain_dir("csg2d") / LAST)["provenance"]["totals"]
    assert tot["cpu_hours_complete"] is False and tot["epochs"] == 2


def test_restart_sets_the_learning_rate_back_and_resume_keeps_it(programs, tmp_path):
    # min_delta so large that no epoch improves: the plateau rule halves the rate after every epoch
    decay = {"lr_patience": 0, "lr_factor": 0.5, "min_delta": 100.0}
    first = run_root(programs, tmp_path, "first")
    pretrain(config(2, train=decay), first)
    init = str(first.pretrain_dir("csg2d") / LAST)
    lrs = {}
    for mode in ("restart", "resume"):
        layout = run_root(programs, tmp_path, mode)
        pretrain(config(1, train=decay, init=init, continue_lr=mode), layout)
        lrs[mode] = float(list(csv.DictReader((layout.pretrain_dir("csg2d") / HISTORY).open()))[-1]["lr"])
    last_first = float(list(csv.DictReader((first.pretrain_dir("csg2d") / HISTORY).open()))[-1]["lr"])
    assert last_first == pytest.approx(5e-4)   # epoch 1 improves on the infinite best, epoch 2 halves
    # restart: a fresh plateau rule's first epoch improves on its infinite best, so the rate stays at lr
    assert lrs["restart"] == pytest.approx(1e-3)
    assert lrs["resume"] == pytest.approx(2.5e-4)


def test_a_resumed_run_takes_the_plateau_rule_of_its_configuration(programs, tmp_path):
    """A killed run resumed with another ``lr_patience`` uses it (the saved scheduler state carries the old
    settings, which were silently kept before)."""
    decay = {"lr_patience": 0, "lr_factor": 0.5, "min_delta": 100.0}
    layout = run_root(programs, tmp_path, "run")
    pretrain(config(2, train=decay), layout)
    pretrain(config(4, train={**decay, "lr_patience": 100}), layout)      # the same folder: a resume
    rows = list(csv.DictReader((layout.pretrain_dir("csg2d") / HISTORY).open()))
    assert [float(r["lr"]) for r in rows] == pytest.approx([1e-3, 5e-4, 5e-4, 5e-4])
    # and the rule as it was goes on halving
    again = run_root(programs, tmp_path, "again")
    pretrain(config(2, train=decay), again)
    pretrain(config(4, train=decay), again)
    rows = list(csv.DictReader((again.pretrain_dir("csg2d") / HISTORY).open()))
    assert [float(r["lr"]) for r in rows] == pytest.approx([1e-3, 5e-4, 2.5e-4, 1.25e-4])


def test_a_zero_epoch_segment_keeps_the_continued_weights(programs, tmp_path):
    first, second = run_root(programs, tmp_path, "first"), run_root(programs, tmp_path, "second")
    pretrain(config(1), first)
    init = first.pretrain_dir("csg2d") / LAST
    summary = pretrain(config(0, init=str(init)), second)
    a, b = read_checkpoint(init)["state_dict"], read_checkpoint(second.pretrain_dir("csg2d") / BEST)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert summary["units"] == 1 and summary["totals"]["epochs"] == 1
    # it leaves a state to continue or ship: the continued one, with the record of what it holds
    last = read_checkpoint(second.pretrain_dir("csg2d") / LAST)
    assert all(torch.equal(a[k], last["state_dict"][k]) for k in a)
    assert last["provenance"]["totals"]["epochs"] == 1 and last["loop"]["unit"] == 1


def test_init_of_another_network_domain_or_a_missing_file_is_one_line(programs, tmp_path):
    first = run_root(programs, tmp_path, "first")
    pretrain(config(1), first)
    init = str(first.pretrain_dir("csg2d") / LAST)
    wider = Architecture(**{**ARCHITECTURE, "d_model": 2 * ARCHITECTURE["d_model"]})
    other = replace(config(1, init=init), model=wider)
    with pytest.raises(ConfigError, match=r"another network than pretrain.csg2d.model \(d_model"):
        pretrain(other, run_root(programs, tmp_path, "other"))
    with pytest.raises(ConfigError, match="not found"):
        pretrain(config(1, init=str(tmp_path / "nope.pt")), run_root(programs, tmp_path, "missing"))
    with pytest.raises(ConfigError, match="curriculum.enabled"):
        pretrain(config(1, True, init=init), run_root(programs, tmp_path, "curr"))
    with pytest.raises(ConfigError, match="continue_lr"):
        pretrain(config(1, init=init, continue_lr="warm"), run_root(programs, tmp_path, "lr"))


def test_a_resumed_run_writes_its_whole_history_again(programs, tmp_path):
    """DVC deletes ``history.csv`` (a plot output) before it runs the stage and keeps ``last.pt`` (persisted):
    the resumed run's history still holds every epoch, and a run with nothing left to do (a zero-epoch
    continuation run again) writes it instead of failing on the missing file."""
    whole, layout = run_root(programs, tmp_path, "whole"), run_root(programs, tmp_path, "run")
    pretrain(config(3), whole)
    pretrain(config(2), layout)
    history = layout.pretrain_dir("csg2d") / HISTORY
    history.unlink()
    pretrain(config(3), layout)
    rows = lambda layout: list(csv.DictReader((layout.pretrain_dir("csg2d") / HISTORY).open()))  # noqa: E731
    assert [r["epoch"] for r in rows(layout)] == ["1", "2", "3"]
    assert [r["train_loss"] for r in rows(layout)] == [r["train_loss"] for r in rows(whole)]

    second = run_root(programs, tmp_path, "second")
    init = str(whole.pretrain_dir("csg2d") / LAST)
    pretrain(config(0, init=init), second)
    first_rows = rows(second)
    (second.pretrain_dir("csg2d") / HISTORY).unlink()
    pretrain(config(0, init=init), second)
    assert rows(second) == first_rows and [r["epoch"] for r in first_rows] == ["1", "2", "3"]
