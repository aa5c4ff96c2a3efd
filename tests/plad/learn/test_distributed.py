"""Data-parallel training with torchrun: 2 CPU processes (gloo on loopback) run the real stage commands.

Each rank records the weights after every optimizer step and every file it
wrote (tests/distributed_worker.py); the ranks must hold identical weights
after each step, rank 1 must write nothing, and a run stopped after one
epoch and started again must take exactly the steps of an uninterrupted one.
"""
from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
import torch

from plad.layout import BEST, HISTORY, LAST, STATE, SUMMARY, Layout
from tests.procs import children, launch, left_behind
from tests.tiny import csg2d_inputs, tiny_pretrain_params

pytestmark = pytest.mark.integration


def written(record: dict, root) -> set[str]:
    return {str(p).removeprefix(str(root) + "/") for p in record["writes"]}


def mlflow_runs(db) -> list[str]:
    with sqlite3.connect(db) as c:
        return [r[0] for r in c.execute("select name from runs order by start_time")]


def state(path) -> dict[str, torch.Tensor]:
    return torch.load(path, weights_only=False)["state_dict"]


def test_two_process_pretraining_keeps_ranks_equal_writes_once_and_resumes(tmp_path, synthetic):
    before = children()
    tiny_pretrain_params(tmp_path / "params.yaml")
    straight, resumed = Layout(tmp_path / "straight"), Layout(tmp_path / "resumed")
    for layout in (straight, resumed):   # both runs train on the same synthetic programs
        layout.synthetic_dir.parent.mkdir(parents=True)
        layout.synthetic_dir.symlink_to(synthetic)

    def stage(root: str, *sets: str) -> list[str]:
        return ["pretrain", "--params", "params.yaml", "--section", "pretrain.csg2d", "--root", root,
                *[f"--set {s}" for s in sets]]

    # launch 1: an uninterrupted run of 2 epochs; the same run stopped after epoch 1 (as a kill after the
    # epoch's commit). Launch 2: the stopped run started again.
    (r0, r1), first = launch(tmp_path, "first", [stage("straight"), stage("resumed", "train.max_epochs=1")])
    [second] = launch(tmp_path, "second", [stage("resumed")])
    assert len(r0["steps"]) == 2 * 4 and r0["steps"] == r1["steps"]   # equal weights after every step
    assert len(set(r0["steps"])) == len(r0["steps"])                   # and they did change
    out = straight.pretrain_dir("csg2d")
    assert {BEST, LAST, HISTORY, SUMMARY} <= {p.split("/")[-1] for p in written(r0, out)}
    for record in (r1, first[1], second[1]):                            # rank 1 wrote nothing, not even to MLflow
        assert record["writes"] == [] and record["sqlite"] == []
    assert json.loads((out / SUMMARY).read_text())["units"] == 2
    assert len((out / HISTORY).read_text().splitlines()) == 1 + 2
    # resumed: the steps of the uninterrupted run, on both ranks, and the same weights
    for rank in (0, 1):
        assert first[rank]["steps"] + second[rank]["steps"] == r0["steps"]
    a, b = state(out / LAST), state(resumed.pretrain_dir("csg2d") / LAST)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert (out / HISTORY).read_text().splitlines()[0] == \
        (resumed.pretrain_dir("csg2d") / HISTORY).read_text().splitlines()[0]
    # one MLflow run per stage command, all rank 0's (the stopped run had finished: its restart is a new run)
    # (nested under the row run of (smoke, csg2d, sp), plad.tracking.rows, made by the first)
    assert mlflow_runs(tmp_path / "mlflow.db") == ["sp"] + ["pretrain"] * 3
    assert left_behind(before) == []


def finetune_params(path) -> None:
    """Tiny fine-tuning of the layout's model on 30 real shapes: lest+st+ws (one round) and rl."""
    block = {"device": "cpu", "threads": 1, "train_limit": 30, "val_limit": 6,
             "methods": {"lest_st_ws": {"method": "lest+st+ws"}, "rl": {"method": "rl"}},
             "plad": {"infer_beam": 2, "infer_batch": 8, "val_beam_epoch": 1, "val_beam_round": 2, "max_rounds": 1,
                      "train": {"batch_size": 8, "steps_per_epoch": 3, "max_epochs": 2, "patience": 3},
                      "ws": {"latent": 4, "hidden": 8, "batch_size": 8, "max_epochs": 2, "steps_per_epoch": 2,
                             "sample_batch": 32}},
             "rl": {"batch_size": 6, "steps_per_epoch": 3, "max_epochs": 2, "val_beam": 2}}
    path.write_text(json.dumps({"finetune": {"base": block, "csg2d": {}}}))


def test_two_process_finetuning_splits_inference_and_keeps_ranks_equal(tmp_path, datasets_dir):
    from plad.data.files import evenly_spaced, load_prepared
    from plad.domains import get_domain
    from plad.learn.pbest import PBest
    from plad.model.checkpoint import load_model
    from plad.model.decode import infer_batched

    before = children()
    domain = get_domain("csg2d")
    layout = Layout(csg2d_inputs(tmp_path, datasets_dir))
    finetune_params(tmp_path / "params.yaml")
    keys = {"lest_st_ws": 2 * 2 + 2 * 3, "rl": 2 * 3}   # optimizer steps: WS 2 epochs of 2, fit 2 of 3; RL 2 of 3
    results = launch(tmp_path, "finetune", [["finetune", "--params", "params.yaml", "--section", "finetune.csg2d",
                                             "--set", f"key={key}"] for key in keys])
    for (key, steps), (r0, r1) in zip(keys.items(), results):
        assert len(r0["steps"]) == steps and r0["steps"] == r1["steps"], key
        assert r1["writes"] == [] and r1["sqlite"] == [], key
        names = {p.split("/")[-1] for p in written(r0, layout.finetune_dir("csg2d", key))}
        assert {BEST, STATE, SUMMARY} <= names, key
        assert str(layout.finetune_summary("csg2d", key)) in r0["writes"], key
    # the round's beam inference was split across the ranks: P_BEST holds what one process infers
    sp, _ = load_model(layout.model("csg2d"))
    train = evenly_spaced(load_prepared(layout.prepared("csg2d"), "train"), 30)   # as train_limit picks
    values, programs, _ = infer_batched(sp, domain, train, 2, 8)
    pbest = PBest.load(layout.finetune_dir("csg2d", "lest_st_ws") / "pbest.npz", domain.metric)
    assert [pbest.program(i) for i in range(30)] == [domain.canonical(p) for p in programs]   # stored canonical
    assert np.allclose(pbest.values, values, atol=1e-9)
    # one stage run per method (rank 0's), each under its row run (plad.tracking.rows)
    names = mlflow_runs(tmp_path / "mlflow.db")
    assert sorted(n for n in names if n in keys) == ["lest_st_ws", "rl"]   # rows: named by method
    assert names.count("finetune") == 2
    assert left_behind(before) == []
