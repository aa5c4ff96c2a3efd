"""The report's inputs (:mod:`plad.eval.report`): each method's results gathered from the pipeline's files or
from MLflow alone into :class:`MethodResult` records, the floor's value, the timed evaluations of the rows beyond
the paper (:class:`Timed`), and where each column's numbers come from (:class:`Column`, from the files'
``provenance`` blocks, files only whatever the source)."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from plad.data.files import DataError
from plad.domains import get_domain
from plad.layout import FLOOR, METRICS, SEARCH, STATE, SUMMARY, Layout, eval_key, search_key, split_effort
from plad.learn.loop import read_state, upgrade_summary
from plad.tracking import (
    PIPELINE_EXPERIMENT,
    RunRecord,
    domain_experiment,
    find_experiments,
    latest_finished_run,
    metric_history,
)


@dataclass
class MethodResult:
    key: str
    test: float | None                                # mean test metric (None: not evaluated)
    curve: list[tuple[float, float]] = field(default_factory=list)   # (training seconds, validation metric)
    train_seconds: float | None = None
    val_best: float | None = None                     # validation metric of the selected model
    rounds: int | None = None
    stopped: str | None = None
    train_shapes: int | None = None                   # real shapes the fine-tuning trained on
    #: a wall-clock limit shaped the number (its training's or its evaluation's); None: not known
    stopped_by_time: bool | None = None

# -- gathering ------------------------------------------------------------------------------------
def from_files(domain: str, keys: list[str], layout: Layout) -> list[MethodResult]:
    out = []
    for key in keys:
        metrics = layout.eval_dir(key, domain) / METRICS
        test = json.loads(metrics.read_text())["test"]["mean"] if metrics.exists() else None
        res = MethodResult(key, test)
        state_file = layout.finetune_dir(domain, key) / STATE
        if state_file.exists():   # read_state/upgrade_summary also read the files of older versions
            res.curve = [(float(r["seconds"]), float(r["val"])) for r in read_state(state_file).history]
        summary = layout.finetune_summary(domain, key)
        if summary.exists():
            s = upgrade_summary(json.loads(summary.read_text()))
            res.stopped, res.train_seconds = s.get("stopped"), s.get("train_seconds")
            res.rounds, res.val_best = s.get("units"), s.get("val")
            res.train_shapes = s.get("train_shapes")
        res.stopped_by_time = number_record(domain, key, layout).stopped_by_time
        out.append(res)
    return out

def floor_from_files(domain: str, layout: Layout) -> float | None:
    """The floor baseline's mean test metric (written with SP's evaluation), None when there is none."""
    path = layout.eval_dir(FLOOR, domain) / METRICS
    if not path.exists():
        return None
    test = json.loads(path.read_text()).get("test")
    return test["mean"] if test else None

def domain_experiments(domain: str, experiment: str | None = None) -> list[str]:
    """The ids of the experiments that hold a domain's stage runs: ``experiment`` when given, else the domain's
    own (``plad-<domain>``) and ``plad``, which held every domain's runs before each had its own (so a store
    written by an older version still gives its report); ``LookupError`` when none exists."""
    return find_experiments([experiment] if experiment else [domain_experiment(domain), PIPELINE_EXPERIMENT])

def floor_from_mlflow(domain: str, experiment: str | None = None) -> float | None:
    """The same from the MLflow store: the floor metric logged by the latest SP evaluation run."""
    experiment_ids = domain_experiments(domain, experiment)
    run = latest_finished_run(experiment_ids, {"plad.stage": "evaluate", "plad.method": "sp", "plad.domain": domain})
    return run.metrics.get(f"floor_test_{get_domain(domain).metric.name}") if run else None

def from_mlflow(domain: str, keys: list[str], experiment: str | None = None) -> list[MethodResult]:
    """The same records from the MLflow store alone (latest finished run per stage and method).

    A run's validation value is the best of its whole history by the metric's
    direction (the selected model), not the value at the highest step (the last round's).
    """
    try:
        experiment_ids = domain_experiments(domain, experiment)
    except LookupError as err:   # no experiment in the store: nothing was tracked there
        raise DataError("MLflow", str(err)) from None
    scorer = get_domain(domain).metric
    metric = scorer.name

    def latest(stage: str, key: str) -> RunRecord | None:
        return latest_finished_run(experiment_ids, {"plad.stage": stage, "plad.method": key, "plad.domain": domain})

    out = []
    for key in keys:
        ev = latest("evaluate", key)
        res = MethodResult(key, ev.metrics.get(f"test_{metric}") if ev else None)
        ft = latest("finetune", key)
        if ft is not None:
            history = metric_history(ft.run_id, "val_at_seconds")
            res.curve = sorted((float(step), float(value)) for step, value in history)
            m = ft.metrics
            res.train_seconds = m.get("train_seconds")
            m = upgrade_summary({**m, "metric": metric})   # runs logged by older versions
            res.rounds = int(m["units"]) if "units" in m else None
            res.train_shapes = int(m["train_shapes"]) if "train_shapes" in m else None
            res.stopped = ft.tags.get("plad.stopped")
            timed = ft.tags.get("plad.stopped_by_time")
            res.stopped_by_time = timed == "True" if timed is not None else res.stopped == "budget"
            # "val" is logged per round (step = round) and once more for the selection; older runs: val_<metric>
            val_key = "val" if "val" in ft.metrics else f"val_{metric}"
            history = metric_history(ft.run_id, val_key) if val_key in ft.metrics else []
            res.val_best = scorer.best_value(v for _, v in history) if history else m.get("val")
        out.append(res)
    return out

# -- where the numbers come from ------------------------------------------------------------------
@dataclass
class NumberRecord:
    """Where one number of a column comes from: the files behind it (its evaluation and, for a trained model,
    its training run's summary), read from their ``provenance`` blocks."""

    key: str
    #: (file, commit or None) of every file behind the number that exists
    commits: list[tuple[str, str | None]] = field(default_factory=list)
    dirty: bool = False
    #: wall seconds of each file behind the number (None: not recorded; a training counts its time across
    #: resumes), by path, so that a column counts a file several of its numbers share (a training's summary
    #: behind its beam sweep and its refined evaluation) once
    walls: dict[str, float | None] = field(default_factory=dict)
    #: a wall-clock limit shaped the number; None: no file says (written before the flag existed)
    stopped_by_time: bool | None = None

    @property
    def wall_seconds(self) -> float:
        return wall_totals(self.walls)[0]

    @property
    def timed_files(self) -> int:
        """Files behind the number that recorded their wall seconds (of :attr:`files`)."""
        return wall_totals(self.walls)[1]

    @property
    def files(self) -> int:
        return len(self.walls)


def wall_totals(walls: dict[str, float | None]) -> tuple[float, int, int]:
    """(wall seconds summed, files that recorded them, files) of per-file wall seconds (None: not recorded)."""
    timed = [w for w in walls.values() if w is not None]
    return sum(timed), len(timed), len(walls)


def _training_summary(domain: str, key: str, layout: Layout) -> Path | None:
    """The run summary of the model behind result ``key`` (SP's pretraining, a method's fine-tuning; a beam of
    the sweep or a refined evaluation: its method's), None for search and the floor."""
    key = split_effort(key)[0]
    if key in (SEARCH, FLOOR):
        return None
    method = key[: -len("_refined")] if key.endswith("_refined") else key
    head, _, beam = method.rpartition("_beam")
    method = head if head and beam.isdigit() else method
    if method == "sp":
        return layout.pretrain_dir(domain) / SUMMARY
    return layout.finetune_summary(domain, method)


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _timed(record: dict) -> bool | None:
    """A metrics file's ``stopped_by_time``; for a run summary written before the flag, its budget stop."""
    if "stopped_by_time" in record:
        return bool(record["stopped_by_time"])
    if "stopped" in record:
        return record["stopped"] == "budget"
    return None


def number_record(domain: str, key: str, layout: Layout) -> NumberRecord:
    """The :class:`NumberRecord` of result ``key`` of ``domain`` from the layout's files."""
    rec = NumberRecord(key)
    paths = [layout.eval_dir(key, domain) / METRICS]
    training = _training_summary(domain, key, layout)
    if training is not None:
        paths.append(training)
    flags = []
    for path in paths:
        data = _read_json(path)
        if data is None:
            continue
        prov = data.get("provenance") or {}
        rec.commits.append((str(path), prov.get("commit")))
        rec.dirty |= bool(prov.get("dirty"))
        wall = prov.get("wall_seconds")
        rec.walls[str(path)] = None
        if wall is not None:
            seconds = float(wall)
            if (data.get("totals") or {}).get("segments", 1) <= 1:
                # a training resumed after a kill: the last call's wall seconds, its loop's time across resumes.
                # Not for a pretraining that continues earlier segments: its train_seconds holds theirs too,
                # which this column did not spend (a resumed continuation counts its last call)
                seconds = max(seconds, float(data.get("train_seconds") or 0.0))
            rec.walls[str(path)] = seconds
        flags.append(_timed(data))
    known = [f for f in flags if f is not None]
    rec.stopped_by_time = any(known) if known else None
    return rec


@dataclass
class Column:
    """Where a domain's column comes from."""

    domain: str
    #: the commit most of the column's files were computed at (None: none recorded)
    commit: str | None
    #: some file at that commit was computed with code or params that differ from it
    dirty: bool
    #: result key -> the other commit(s) behind it ("not recorded" for files without provenance)
    others: dict[str, list[str]]
    wall_seconds: float
    timed_files: int
    files: int
    #: result keys whose numbers a wall-clock limit shaped
    stopped_by_time: list[str]
    #: result keys whose files do not say whether a limit shaped them (written before the flag)
    stop_unknown: list[str]
    #: result key -> its record
    records: dict[str, NumberRecord] = field(default_factory=dict)


NOT_RECORDED = "not recorded"


def column(domain: str, keys: list[str], layout: Layout) -> Column:
    """The :class:`Column` of ``domain`` over result ``keys`` (the table's rows, the rows beyond the paper, the
    amortization sweep's) and the floor: the files of their evaluations and trainings."""
    records = {k: number_record(domain, k, layout) for k in dict.fromkeys([*keys, FLOOR])}
    records = {k: r for k, r in records.items() if r.files}
    counts: dict[str, int] = {}
    for r in records.values():
        for _, c in r.commits:
            if c is not None:
                counts[c] = counts.get(c, 0) + 1
    main = max(counts, key=lambda c: counts[c]) if counts else None   # ties: the first one met, row order
    others: dict[str, list[str]] = {}
    for k, r in records.items():
        differ = sorted({c or NOT_RECORDED for _, c in r.commits if c != main})
        if differ and main is not None:
            others[k] = differ
    dirty = any(r.dirty for r in records.values() if any(c == main for _, c in r.commits))
    # each file once: a training's summary is behind several numbers of its column
    wall, timed_files, files = wall_totals({path: w for r in records.values() for path, w in r.walls.items()})
    return Column(domain, main, dirty, others, wall, timed_files, files,
                  [k for k, r in records.items() if r.stopped_by_time],
                  [k for k, r in records.items() if r.stopped_by_time is None], records)

# -- beyond the paper: rows with their time per shape ------------------------------------------------
@dataclass
class Timed:
    """An evaluation's mean test metric and wall-clock seconds per shape (network and refinement parts)."""

    key: str
    test: float
    seconds_per_shape: float
    network_seconds_per_shape: float | None = None
    refine_seconds_per_shape: float | None = None
    n: int = 0


def timed_from_files(domain: str, keys: list[str], layout: Layout) -> dict[str, Timed | None]:
    """{result key: its :class:`Timed` from ``results/eval/<key>/<domain>/metrics.json``, or None if absent}."""
    out: dict[str, Timed | None] = {}
    for key in keys:
        path = layout.eval_dir(key, domain) / METRICS
        if not path.exists():
            out[key] = None
            continue
        test = json.loads(path.read_text()).get("test")
        if not test:
            out[key] = None
            continue
        n = int(test["n"])
        per = test.get("seconds_per_shape", test["seconds"] / max(n, 1))   # files of older versions: no split
        out[key] = Timed(key, float(test["mean"]), float(per), test.get("network_seconds_per_shape"),
                         test.get("refine_seconds_per_shape"), n)
    return out

def amortization_keys(method: str, beams: list[int],
                      efforts: list[str] | tuple[str, ...] = ()) -> list[tuple[str, str]]:
    """(result key, kind) of the amortization picture: the network at each beam, with refinement, search only; then
    per effort level (least work first) network + refinement and search only at that level."""
    keys = [*((eval_key(method, beam=b), "network") for b in beams),
            (eval_key(method, refine=True), "network + refinement"), (SEARCH, "search only")]
    for level in efforts:
        keys += [(eval_key(method, effort=level), "network + refinement"), (search_key(level), "search only")]
    return list(dict.fromkeys(keys))
