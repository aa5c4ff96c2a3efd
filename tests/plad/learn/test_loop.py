"""The one budgeted, resumable loop: direction, patience, budget, resume after a kill, old files."""
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from plad.layout import Layout
from plad.learn import loop as loop_module
from plad.learn.loop import JsonStore, Limits, Loop, Objective, Unit, read_state, upgrade_state, upgrade_summary
from plad.metrics import IOU
from tests.conftest import REPO_ROOT

REPO = REPO_ROOT
LOSS = Objective("loss", higher_is_better=False)


class Clock:
    """A fake ``time.monotonic`` that only moves when a unit says so."""

    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch):
    c = Clock()
    monkeypatch.setattr(loop_module.time, "monotonic", c)
    return c


def scripted(values, clock=None, seconds=1.0, patience=None):
    """A step that reports ``values[unit - 1]`` and takes ``seconds`` of the fake clock."""
    calls = []

    def step(unit, remaining):
        calls.append(unit)
        if clock is not None:
            clock.now += seconds
        return Unit(values[unit - 1], {"x": unit * 10}, **({} if patience is None else {"patience": patience}))
    return step, calls


def test_the_direction_comes_from_the_objective():
    values = [0.5, 0.7, 0.6, 0.2]
    for objective, best, best_unit in [(IOU, 0.7, 2), (LOSS, 0.2, 4)]:
        kept = []
        step, _ = scripted(values)
        result = Loop("epoch", objective, Limits(max_units=4)).run(step, keep_best=lambda u, v, k=kept: k.append(u))
        assert (result.best, result.best_unit, result.stopped, result.units) == (best, best_unit, "max_epochs", 4)
        assert kept == ([1, 2] if objective is IOU else [1, 4])


def test_min_delta_and_patience():
    # IoU: +0.005 does not beat min_delta 0.01; three units without a gain > 0.01 stop the loop
    step, calls = scripted([0.5, 0.505, 0.509, 0.508, 0.9])
    result = Loop("round", IOU, Limits(max_units=10, patience=3, min_delta=0.01)).run(step)
    assert calls == [1, 2, 3, 4] and result.stopped == "patience" and (result.best, result.best_unit) == (0.5, 1)
    # a unit may spend more patience than 1 (a PLAD round spends its epochs)
    step, calls = scripted([0.5, 0.4, 0.4, 0.4], patience=2)
    result = Loop("round", IOU, Limits(max_units=10, patience=3)).run(step)
    assert calls == [1, 2, 3] and result.stopped == "patience"


def test_history_has_the_fixed_schema_and_restore_best_runs_last():
    events = []
    step, _ = scripted([3.0, 2.0, 2.5])
    result = Loop("round", LOSS, Limits(max_units=3)).run(
        step, start=lambda: 4.0, keep_best=lambda u, v: events.append(("keep", u)),
        restore_best=lambda: events.append(("restore",)), on_unit=lambda u, row: events.append(("unit", u)))
    assert [list(r)[:2] for r in result.history] == [["unit", "val"]] * 4
    assert [(r["unit"], r["val"]) for r in result.history] == [(0, 4.0), (1, 3.0), (2, 2.0), (3, 2.5)]
    assert all(r["seconds"] >= 0 and r["unit_seconds"] >= 0 for r in result.history)
    assert result.history[1]["x"] == 10
    assert events == [("keep", 0), ("keep", 1), ("unit", 1), ("keep", 2), ("unit", 2), ("unit", 3), ("restore",)]
    assert result.summary() == {"unit_name": "round", "units": 3, "best_unit": 2, "val": 2.0,
                                "stopped": "max_rounds", "stopped_by_time": False,
                                "train_seconds": round(result.seconds, 1)}


def test_budget_in_seconds_across_resumes(tmp_path, clock):
    # 4 s per unit, 10 s budget: the third unit starts at 8 s and ends at 12 s, then the loop stops
    step, calls = scripted([5.0, 4.0, 3.0, 2.0, 1.0], clock, seconds=4.0)
    result = Loop("epoch", LOSS, Limits(max_units=5, budget_seconds=10.0)).run(step)
    assert calls == [1, 2, 3] and result.stopped == "budget" and result.seconds == 12.0
    # the same across a resume: 2 units (8 s), then the rest of the budget runs one more unit
    store = JsonStore(tmp_path / "state.json")
    step, calls = scripted([5.0, 4.0, 3.0, 2.0, 1.0], clock, seconds=4.0)
    Loop("epoch", LOSS, Limits(max_units=2, budget_seconds=10.0), store).run(step)
    result = Loop("epoch", LOSS, Limits(max_units=5, budget_seconds=10.0), store).run(step)
    assert calls == [1, 2, 3] and result.stopped == "budget" and result.seconds == 12.0
    # the remaining budget an inner loop gets counts the time this unit has used
    seen = []

    def inner(unit, remaining):
        clock.now += 1.5
        seen.append(remaining())
        clock.now += 1.0
        return Unit(1.0)
    Loop("round", LOSS, Limits(max_units=2, budget_seconds=10.0)).run(inner)
    assert seen == [8.5, 6.0]


def test_a_result_says_whether_a_wall_clock_limit_shaped_it(clock):
    # the work (max_units) ends the loop before the budget: not stopped by time, whatever the clock says
    step, _ = scripted([3.0, 2.0], clock, seconds=4.0)
    result = Loop("epoch", LOSS, Limits(max_units=2, budget_seconds=8.0)).run(step)
    assert result.stopped == "max_epochs" and result.seconds == 8.0
    assert result.summary()["stopped_by_time"] is False and "stopped_by_time" not in result.history[-1]
    # the budget (the safety net) ends it: stopped by time
    step, _ = scripted([3.0, 2.0, 1.0], clock, seconds=4.0)
    result = Loop("epoch", LOSS, Limits(max_units=3, budget_seconds=8.0)).run(step)
    assert result.stopped == "budget" and result.summary()["stopped_by_time"] is True
    # a unit whose own work a time limit cut short (an inner loop, a search step): its row and the result say so

    def cut(unit, remaining):
        return Unit(1.0 / unit, stopped_by_time=unit == 2)
    result = Loop("round", LOSS, Limits(max_units=3)).run(cut)
    assert result.stopped == "max_rounds" and result.summary()["stopped_by_time"] is True
    assert [r.get("stopped_by_time", False) for r in result.history] == [False, True, False]


def test_a_loop_runs_one_unit_even_without_budget_left(clock):
    # an inner loop started when the outer one has spent its budget still trains once (it must have a best)
    step, calls = scripted([1.0, 0.5], clock, seconds=1.0)
    result = Loop("epoch", LOSS, Limits(max_units=2, budget_seconds=-3.0)).run(step)
    assert calls == [1] and result.stopped == "budget" and result.best_unit == 1


class Trainer:
    """A toy trainer with state on disk: a value that follows a seeded random walk."""

    def __init__(self, out: Path, kill_at: int | None = None, kill_in_commit: int | None = None):
        self.out, self.kill_at, self.kill_in_commit = out, kill_at, kill_in_commit
        self.w = 0.0
        self.calls: list[int] = []

    def step(self, unit, remaining):
        if unit == self.kill_at:
            raise KeyboardInterrupt   # a kill during the unit
        self.calls.append(unit)
        rng = np.random.default_rng([7, unit])   # data derived from the unit, as every trainer does
        self.w += float(rng.normal())
        return Unit(abs(self.w), {"w": self.w}, patience=1)

    def save(self, unit, folder):
        (folder / "weights.json").write_text(json.dumps({"w": self.w, "unit": unit}))
        if unit == self.kill_in_commit:
            raise KeyboardInterrupt   # a kill after the caller's files, before the loop state

    def restore(self):
        self.w = json.loads((self.out / "weights.json").read_text())["w"]

    def run(self, max_units=8):
        store = JsonStore(self.out / "state.json", save=self.save, restore=self.restore)
        return Loop("round", LOSS, Limits(max_units=max_units, patience=4), store).run(self.step, start=lambda: 0.5)


def strip(history):
    return [{k: v for k, v in row.items() if "seconds" not in k} for row in history]


@pytest.mark.parametrize("kill", [{"kill_at": 4}, {"kill_in_commit": 4}])
def test_resume_after_a_kill_continues_at_the_next_unit_with_the_same_result(tmp_path, kill):
    straight_dir, killed_dir = tmp_path / "straight", tmp_path / "killed"
    straight_dir.mkdir(), killed_dir.mkdir()
    straight = Trainer(straight_dir).run()
    first = Trainer(killed_dir, **kill)
    with pytest.raises(KeyboardInterrupt):
        first.run()
    assert read_state(killed_dir / "state.json").unit == 3       # units 1-3 are finished
    again = Trainer(killed_dir)
    resumed = again.run()
    assert again.calls[0] == 4                                     # it continues with unit 4
    assert strip(resumed.history) == strip(straight.history)
    assert (resumed.units, resumed.best_unit, resumed.best, resumed.stopped) == \
        (straight.units, straight.best_unit, straight.best, straight.stopped)
    # a finished run started again does nothing more
    done = Trainer(killed_dir)
    assert done.run().units == straight.units and done.calls == []


def test_files_of_earlier_versions_read_into_the_schema():
    rounds = {"round": 2, "best": 1.5, "best_round": 1, "epochs_since_best": 8, "seconds": 12.0,
              "history": [{"round": 0, "val_chamfer": 2.0, "seconds": 0.0},
                          {"round": 1, "val_chamfer": 1.5, "pbest_mean": 1.2, "epochs": 8, "round_seconds": 6.0,
                           "seconds": 6.0}]}
    s = upgrade_state(rounds, "round")
    assert (s["unit"], s["best_unit"], s["since_best"], s["unit_name"]) == (2, 1, 8, "round")
    assert s["history"][1] == {"unit": 1, "val": 1.5, "pbest_mean": 1.2, "epochs": 8, "unit_seconds": 6.0,
                               "seconds": 6.0}
    fit = upgrade_state({"epoch": 3, "best": 0.7, "best_epoch": 2, "bad_epochs": 1, "seconds": 9.0}, "epoch")
    assert (fit["unit"], fit["best_unit"], fit["since_best"], fit["history"]) == (3, 2, 1, [])
    old = {"method": "rl", "epochs": 20, "best_epoch": 9, "val_chamfer": 2.4, "stopped": "budget", "metric": "chamfer"}
    assert upgrade_summary(old) == {"method": "rl", "units": 20, "best_unit": 9, "val": 2.4, "stopped": "budget",
                                    "metric": "chamfer"}
    # MLflow metrics of an old PLAD run: its summary's "rounds", not its rows' "epochs"
    assert upgrade_summary({"rounds": 3, "epochs": 8, "metric": "iou", "val_iou": 0.5})["units"] == 3


def test_report_reads_the_committed_summaries_and_old_state_files(tmp_path):
    from plad.eval.report import from_files

    layout = Layout(tmp_path)
    state = layout.finetune_dir("csg2d", "lest_st") / "state.json"
    state.parent.mkdir(parents=True)
    state.write_text(json.dumps({"round": 1, "best": 1.9, "best_round": 1, "epochs_since_best": 0, "seconds": 300.0,
                                 "history": [{"round": 0, "val_chamfer": 2.2, "seconds": 0.0},
                                             {"round": 1, "val_chamfer": 1.9, "seconds": 300.0}]}))
    committed = json.loads(Layout(REPO).finetune_summary("csg2d", "lest_st").read_text())
    layout.finetune_summary("csg2d", "lest_st").parent.mkdir(parents=True)
    shutil.copy(Layout(REPO).finetune_summary("csg2d", "lest_st"), layout.finetune_summary("csg2d", "lest_st"))
    (r,) = from_files("csg2d", ["lest_st"], layout)
    assert r.curve == [(0.0, 2.2), (300.0, 1.9)]
    expected = upgrade_summary(committed)
    assert (r.rounds, r.val_best, r.stopped, r.train_seconds) == \
        (expected["units"], expected["val"], committed["stopped"], committed["train_seconds"])
    assert r.rounds is not None and math.isfinite(r.val_best)
