"""The one budgeted, resumable loop over units of work, shared by every trainer.

Pretraining (:func:`plad.learn.train.fit`, unit: epoch), the PLAD rounds
(:func:`plad.learn.rounds.run_rounds`, unit: round), REINFORCE
(:func:`plad.learn.rl.run_rl`, unit: epoch) and the wake-sleep generator
(:func:`plad.learn.ws.train_generator`, unit: epoch) differ only in what one unit
does. What they share lives here, once:

* the best value so far and its direction, taken from the objective (a
  :class:`plad.metrics.Metric` or an :class:`Objective`; both declare
  ``higher_is_better``): a unit improves when it beats the best by more
  than ``min_delta``;
* patience: the loop stops once the units since the last improvement have
  spent ``patience`` (a unit spends 1 unless it says otherwise: a PLAD round
  spends its training epochs);
* a wall-clock budget in seconds, summed over the units of all resumes; a
  loop runs at least one unit before the budget can stop it, so that every
  loop ends with a best model even when an outer loop left it no time. The
  profiles fix the work (``max_units``, patience) and keep the budget as a
  safety net only: a result is a function of code, params and data unless
  the budget stopped the loop or something inside a unit (an inner loop, a
  time-limited search), which the summary says (``stopped_by_time``);
* persistence through a store: after each unit the caller's state and the
  loop state are written so that a killed run, started again, continues
  after the last finished unit (``store=None``: in memory only);
* the history, one row per unit with a fixed schema: ``unit`` (the index;
  0 is the evaluation before any training, when there is one), ``val`` (the
  value the loop selects on), ``seconds`` (budget time spent so far) and
  ``unit_seconds``, followed by whatever the unit reports.

Callers keep the best weights through ``keep_best`` and get them back through
``restore_best``; the loop decides when.

In a distributed run (:mod:`plad.learn.distributed`) every rank runs the loop; the
decisions are rank 0's (its limits, and each unit's value and time, are
broadcast), and only rank 0 commits the store and hears ``on_unit``.
``keep_best`` and ``restore_best`` run on every rank: ``keep_best`` writes
files only on rank 0, and ``restore_best`` runs once every rank is past the
last ``keep_best``.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

from tqdm import tqdm

from plad.fsutil import atomic_write_text
from plad.learn import distributed as dist

log = logging.getLogger(__name__)


class Direction(Protocol):
    """Anything that declares its direction: :class:`Objective`, :class:`plad.metrics.Metric`."""

    @property
    def higher_is_better(self) -> bool: ...


@dataclass(frozen=True)
class Objective:
    """A value to select on that is not a domain metric, e.g. a loss. ``name``: its key in a metrics dict."""

    name: str
    higher_is_better: bool


def gain(objective: Direction, value: float, reference: float) -> float:
    """How much better ``value`` is than ``reference`` (positive: better), in the objective's direction."""
    return value - reference if objective.higher_is_better else reference - value


def worst(objective: Direction) -> float:
    """A starting best that any finite value improves on."""
    return -math.inf if objective.higher_is_better else math.inf


def budget_seconds(max_minutes: float | None) -> float:
    """The config's budget (minutes, None: none) in the seconds every loop counts in."""
    return math.inf if max_minutes is None else max_minutes * 60


@dataclass
class Limits:
    """When a loop stops: ``max_units`` done, ``patience`` spent without improvement, or the budget (units
    and budget of the current segment, see :attr:`LoopState.segment_unit`)."""

    max_units: int
    patience: float = math.inf
    #: the smallest gain over the best that counts as an improvement
    min_delta: float = 0.0
    budget_seconds: float = math.inf


@dataclass
class Unit:
    """What one unit reports: the value to select on, extra history columns, patience spent if not better."""

    value: float
    row: dict[str, Any] = field(default_factory=dict)
    patience: float = 1
    #: a time limit cut the unit's work short (an inner loop's budget, a search's time limit): its history
    #: row gets ``stopped_by_time: true``
    stopped_by_time: bool = False


@dataclass
class LoopState:
    """Everything the loop itself needs to resume (JSON-serializable)."""

    unit_name: str
    unit: int = 0                   # units finished (unit 0, the start evaluation, not counted)
    best: float = math.nan
    best_unit: int = 0
    since_best: float = 0           # patience spent since the best unit
    seconds: float = 0.0            # budget time spent, over all resumes
    history: list[dict[str, Any]] = field(default_factory=list)
    #: units and seconds done before this segment: a run continued from another run's state (a pretraining
    #: continued from a checkpoint, plad.learn.pretrain) counts its limits from here; 0 for a fresh run
    segment_unit: int = 0
    segment_seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], unit_name: str) -> LoopState:
        """Read a saved state, including the files written before this module existed (see :func:`upgrade_state`)."""
        d = upgrade_state(d, unit_name)
        return cls(**{k: d[k] for k in ("unit_name", "unit", "best", "best_unit", "since_best", "seconds",
                                        "history", "segment_unit", "segment_seconds") if k in d})

    def new_segment(self, objective: Direction) -> LoopState:
        """This state as the start of a new segment: its units, time and history kept, its limits counted from
        here, and the best forgotten (a segment selects its best on its own validation data)."""
        return dataclasses.replace(self, best=worst(objective), best_unit=self.unit, since_best=0,
                                   segment_unit=self.unit, segment_seconds=self.seconds,
                                   history=list(self.history))


@dataclass
class LoopResult:
    unit_name: str
    units: int
    best_unit: int
    best: float
    stopped: str             # "patience", "budget" or f"max_{unit_name}s"
    seconds: float
    history: list[dict[str, Any]]

    @property
    def stopped_by_time(self) -> bool:
        """Whether a wall-clock limit shaped the result: the budget stopped the loop, or cut a unit's work."""
        return self.stopped == "budget" or any(bool(r.get("stopped_by_time")) for r in self.history)

    def summary(self) -> dict[str, Any]:
        """The run summary every trainer reports (results/finetune/*.json, pretrain's summary.json)."""
        return {"unit_name": self.unit_name, "units": self.units, "best_unit": self.best_unit, "val": self.best,
                "stopped": self.stopped, "stopped_by_time": self.stopped_by_time,
                "train_seconds": round(self.seconds, 1)}


class Store(Protocol):
    """Where a loop's state goes between units.

    ``load()`` restores the caller's state of the last finished unit and
    returns the loop state saved with it (None: a fresh run); ``commit(state)``
    saves both, consistently: one atomic file (:func:`plad.learn.train.fit`'s
    ``last.pt``) or a staged commit (:class:`JsonStore`). A commit is the end
    of a unit; a kill before it redoes the unit.
    """

    def load(self) -> dict[str, Any] | None: ...

    def commit(self, state: dict[str, Any]) -> None: ...


class JsonStore:
    """Loop state in a JSON file (``state.json``, also the run's readable history), with the caller's files.

    A two-step commit keeps the two consistent whenever the process dies:
    ``save(unit, folder)`` writes the caller's files (weights, P_BEST, ...)
    into a staging folder beside the state file; the state file is then
    written atomically, which is the commit; then the staged files replace
    the previous ones. On resume, files staged for the committed unit are
    moved into place, and files staged for a unit that never committed are
    dropped; ``restore()`` then reads the caller's files.
    """

    def __init__(self, path: str | Path, save: Callable[[int, Path], None] | None = None,
                 restore: Callable[[], None] | None = None):
        self.path = Path(path)
        self.save, self.restore = save, restore

    def _staged(self) -> dict[int, Path]:
        return {int(p.name.rsplit("-", 1)[1]): p for p in self.path.parent.glob(f".{self.path.stem}-unit-*")}

    def _promote(self, folder: Path) -> None:
        for f in folder.iterdir():
            os.replace(f, self.path.parent / f.name)
        folder.rmdir()

    def load(self) -> dict[str, Any] | None:
        state = json.loads(self.path.read_text()) if self.path.exists() else None
        unit = upgrade_state(state, "unit")["unit"] if state is not None else None
        for k, folder in self._staged().items():
            if k == unit:
                self._promote(folder)     # killed after the commit, before the files were moved
            else:
                shutil.rmtree(folder)     # killed before the commit: that unit is redone
        if state is not None and self.restore:
            self.restore()
        return state

    def commit(self, state: dict[str, Any]) -> None:
        folder = None
        if self.save:
            folder = self.path.parent / f".{self.path.stem}-unit-{int(state['unit'])}"
            folder.mkdir(parents=True, exist_ok=True)
            self.save(int(state["unit"]), folder)
        atomic_write_text(self.path, json.dumps(state, indent=2) + "\n")
        if folder is not None:
            self._promote(folder)


def read_state(path: str | Path, unit_name: str = "unit") -> LoopState:
    """A loop's ``state.json`` (any version), e.g. for the report."""
    return LoopState.from_dict(json.loads(Path(path).read_text()), unit_name)


class Loop:
    """Run units until ``limits`` stop it; see the module docstring for what the loop owns."""

    def __init__(self, unit_name: str, objective: Direction, limits: Limits, store: Store | None = None):
        self.unit_name, self.objective, self.limits, self.store = unit_name, objective, limits, store

    def _stop(self, s: LoopState) -> str | None:
        lim = self.limits
        if s.unit - s.segment_unit >= lim.max_units:
            return f"max_{self.unit_name}s"
        if s.since_best >= lim.patience:
            return "patience"
        # at least one unit per loop before the budget applies (see the module docstring)
        if s.unit > s.segment_unit and s.seconds - s.segment_seconds >= lim.budget_seconds:
            return "budget"
        return None

    def run(self, step: Callable[[int, Callable[[], float]], Unit], *,
            start: Callable[[], float] | None = None,
            keep_best: Callable[[int, float], None] | None = None,
            restore_best: Callable[[], None] | None = None,
            on_unit: Callable[[int, dict[str, Any]], None] | None = None,
            progress: str | None = None) -> LoopResult:
        """Resume or start, run units, restore the best, and return the result.

        ``step(unit, remaining)`` runs unit ``unit`` (1-based); ``remaining()``
        is the budget left in seconds, counting the time this unit has used so
        far (for inner loops). ``start()`` (fresh runs only) evaluates the
        starting point as unit 0, which then is the best to beat.
        ``keep_best(unit, value)`` saves a new best; ``restore_best()`` loads it
        back at the end. ``on_unit(unit, row)`` follows each unit's commit.
        """
        saved = dist.main_first(self.store.load) if self.store else None
        self.limits = dist.broadcast(self.limits)   # budgets computed from each rank's clock: rank 0's rule
        if saved is not None:
            s = LoopState.from_dict(saved, self.unit_name)
            if dist.is_main() and s.unit == s.segment_unit > 0:   # a new segment of a continued run (no epoch
                # of a segment is committed before its first one ends, so this is never a resume)
                print(f"continuing after {self.unit_name} {s.unit} ({s.seconds:.0f} s trained before) as a new "
                      f"segment", file=sys.stderr)
            elif dist.is_main():   # the user sees that the run continues, and from where
                print(f"resuming from {self.unit_name} {s.unit + 1} ({s.unit} finished, {s.seconds:.0f} s of "
                      f"budget spent; best {s.best:.6g} at {self.unit_name} {s.best_unit})", file=sys.stderr)
        else:
            s = LoopState(self.unit_name, best=worst(self.objective))
            if start is not None:
                value = dist.broadcast(start())
                s.best = value
                s.history.append({"unit": 0, "val": value, "unit_seconds": 0.0, "seconds": 0.0})
                if keep_best:
                    keep_best(0, value)
                if self.store and dist.is_main():
                    self.store.commit(s.to_dict())
        bar = tqdm(total=s.segment_unit + self.limits.max_units, initial=s.unit, desc=progress, unit=self.unit_name,
                   disable=None if progress and dist.is_main() else True)
        while (stopped := self._stop(s)) is None:
            unit = s.unit + 1
            t0 = time.monotonic()
            spent = s.seconds

            def remaining(spent: float = spent - s.segment_seconds, t0: float = t0) -> float:
                return self.limits.budget_seconds - spent - (time.monotonic() - t0)

            result = step(unit, remaining)
            dt = time.monotonic() - t0
            result, dt = dist.broadcast((result, dt))
            s.unit, s.seconds = unit, s.seconds + dt
            if gain(self.objective, result.value, s.best) > self.limits.min_delta:
                s.best, s.best_unit, s.since_best = result.value, unit, 0
                if keep_best:
                    keep_best(unit, result.value)
            else:
                s.since_best += result.patience
            row = {"unit": unit, "val": result.value, **result.row, "unit_seconds": dt, "seconds": s.seconds}
            if result.stopped_by_time:
                row["stopped_by_time"] = True
            s.history.append(row)
            if self.store and dist.is_main():
                self.store.commit(s.to_dict())   # the unit is finished once this is on disk
            bar.update(1)
            bar.set_postfix(val=f"{result.value:.4g}", best=f"{s.best:.4g}")
            if on_unit and dist.is_main():
                on_unit(unit, row)
        bar.close()
        if restore_best:
            dist.barrier()   # rank 0 has written the last best
            restore_best()
        return LoopResult(self.unit_name, s.unit, s.best_unit, s.best, stopped, s.seconds, s.history)


# -- files written before this module --------------------------------------------------------------
# The committed results and any run in progress were written by three separate loops with their own
# key names. These functions read them into the schema above; nothing else should sniff key names.
_UNIT_KEYS = ("round", "epoch")


def upgrade_row(row: dict[str, Any]) -> dict[str, Any]:
    """An old history row ({"round"|"epoch": k, "val_<metric>": v, ...}) in the fixed schema."""
    if "unit" in row and "val" in row:
        return row
    out: dict[str, Any] = {}
    for k, v in row.items():
        if k in _UNIT_KEYS:
            out["unit"] = v
        elif k.startswith("val_") and "val" not in out:
            out["val"] = v
        elif k in ("round_seconds", "epoch_seconds"):
            out["unit_seconds"] = v
        else:
            out[k] = v
    return out


def upgrade_state(d: dict[str, Any], unit_name: str) -> dict[str, Any]:
    """An old loop state (PLAD rounds' or RL's ``state.json``, fit's ``train_state``) in the current keys."""
    if "unit" in d:
        return d
    unit_key = next((k for k in _UNIT_KEYS if k in d), None)
    return {"unit_name": unit_key or unit_name,
            "unit": d.get(unit_key, 0) if unit_key else 0,
            "best": d["best"],
            "best_unit": d.get("best_round", d.get("best_epoch", 0)),
            "since_best": d.get("epochs_since_best", d.get("bad_epochs", 0)),
            "seconds": d.get("seconds", 0.0),
            "history": [upgrade_row(r) for r in d.get("history", [])]}


def upgrade_summary(s: dict[str, Any]) -> dict[str, Any]:
    """An old run summary ("rounds"/"epochs", "best_round"/"best_epoch", "val_<metric>") in the current keys."""
    if "units" in s:
        return s
    out = dict(s)
    # the first old key present wins: a PLAD summary's "rounds" before its rows' "epochs" (MLflow metrics)
    for new, olds in (("units", ("rounds", "epochs")), ("best_unit", ("best_round", "best_epoch")),
                      ("val", (f"val_{s.get('metric')}",))):
        old = next((k for k in olds if k in out), None)
        if old is not None:
            out[new] = out.pop(old)
    return out
