"""The results report: the paper's Table 1 layout, convergence curves, the P_BEST ablation.

Beyond the paper: rows with search (search only, a search-seeded P_BEST,
test-time refinement) with their seconds per shape, and the amortization
picture (metric against seconds per shape). These come from the evaluation
files only (:class:`Timed`); a missing one is named in the report, never an
error, so a profile or a partial run without them still gets its report.

Inputs are gathered per method either from the pipeline's files (the
evaluation ``metrics.json`` and fine-tuning ``state.json``/``summary.json``)
or from MLflow alone (the ``evaluate`` and ``finetune`` runs' metrics), into
the same :class:`MethodResult` records, so the report can be rebuilt from
either. Rendering is a pure function of those records.

Where each column's numbers come from (:class:`Column`, from the files'
``provenance`` blocks, :mod:`plad.provenance`; files only, whatever the
source): the commit most of them were computed at, the numbers from another
commit (or with none recorded), the stages' wall time, and the results a
wall-clock limit shaped ("stopped by time"). The tables mark those numbers.
"""
from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from plad.data.files import DataError
from plad.domains import get_domain
from plad.fsutil import atomic_write
from plad.layout import FLOOR, METRICS, SEARCH, STATE, SUMMARY, Layout, eval_key
from plad.learn.loop import read_state, upgrade_summary
from plad.learn.method_registry import key_label
from plad.tracking import (
    PIPELINE_EXPERIMENT,
    RunRecord,
    domain_experiment,
    find_experiments,
    latest_finished_run,
    metric_history,
)

#: the rows that are no fine-tuning method; a method's label is what it declares (:func:`key_label`)
LABELS = {"sp": "SP", SEARCH: "search, no network", FLOOR: "floor"}


def label(key: str) -> str:
    if key in LABELS:
        return LABELS[key]
    if (declared := key_label(key)) is not None:
        return declared
    if key.endswith("_refined"):
        return label(key[: -len("_refined")]) + " + test-time refinement"
    head, _, beam = key.rpartition("_beam")
    if head and beam.isdigit():
        return f"{label(head)}, beam {beam}"
    return key.replace("_per_round", " (per-round)").replace("_", "+").upper().replace("(PER-ROUND)", "(per-round)")


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


def floor_label(domains: list[str]) -> str:
    """The floor row's label: what each domain's floor is, e.g. ``Floor: one box (3D CSG, ShapeAssembly)``."""
    by: dict[str, list[str]] = {}
    for d in domains:
        name = get_domain(d).floor_name
        if name:
            by.setdefault(name, []).append(_title(d))
    return "Floor: " + ", ".join(f"{name} ({', '.join(titles)})" for name, titles in by.items())


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


def _hours(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60} min" if minutes >= 60 else f"{seconds / 60:.1f} min"


def _short(commit: str | None) -> str:
    return commit[:7] if commit and commit != NOT_RECORDED else (commit or NOT_RECORDED)


#: marks of a number in the tables (explained under the tables)
OTHER_COMMIT, BY_TIME = "*", "†"


def marks(columns: dict[str, Column] | None, domain: str, key: str) -> str:
    """The marks of result ``key`` in ``domain``'s column: another commit, stopped by time."""
    c = (columns or {}).get(domain)
    if c is None:
        return ""
    return (OTHER_COMMIT if key in c.others else "") + (BY_TIME if key in c.stopped_by_time else "")


def columns_markdown(columns: dict[str, Column], listed: list[str] | None = None) -> str:
    """Per column: its commit, the numbers from another commit, the stages' wall time, what stopped by time.

    ``listed``: the result keys named in the rows on other commits and stops (the floor always; default: all);
    the commit and the wall time count every number of the column.
    """
    domains = list(columns)
    named = None if listed is None else {*listed, FLOOR}

    def keys(found) -> list[str]:
        return [k for k in found if named is None or k in named]
    lines = ["## Where the numbers come from", "",
             f"Per column: the commit of its numbers (the one most of its files name; {OTHER_COMMIT}: a number "
             f"from another commit, or without one recorded), the wall time of the stages behind them (summed: "
             f"pretraining, fine-tuning, evaluations, search; the files that recorded it), and the "
             f"numbers a wall-clock limit shaped ({BY_TIME}, stopped by time: rerunning them on another machine "
             f"gives other numbers; the others are a function of code, params and data).", "",
             "| | " + " | ".join(_title(d) for d in domains) + " |", "|---|" + "---|" * len(domains)]

    def row(name: str, cell) -> None:
        lines.append(f"| {name} | " + " | ".join(cell(columns[d]) for d in domains) + " |")

    row("commit", lambda c: _short(c.commit) + (" (dirty)" if c.dirty else ""))
    row(f"{OTHER_COMMIT} from another commit",
        lambda c: ", ".join(f"{label(k)} ({', '.join(_short(x) for x in c.others[k])})" for k in keys(c.others))
        or "—")
    row("stages' wall time", lambda c: (f"{_hours(c.wall_seconds)} ({c.timed_files} of {c.files} files)"
                                        if c.timed_files else NOT_RECORDED))

    def stop(c: Column) -> str:
        parts = []
        if keys(c.stopped_by_time):
            parts.append(f"{BY_TIME} by time: " + ", ".join(label(k) for k in keys(c.stopped_by_time)))
        if keys(c.stop_unknown):
            parts.append("not recorded: " + ", ".join(label(k) for k in keys(c.stop_unknown)))
        return "; ".join(parts) or "work (every run ended on its epochs, rounds or patience)"

    row("stop", stop)
    return "\n".join(lines) + "\n"


def columns_json(columns: dict[str, Column]) -> dict[str, dict]:
    """The columns for ``report.json``: commit, other commits, wall time, stops, and each number's commits."""
    return {d: {"commit": c.commit, "dirty": c.dirty, "other_commits": c.others,
                "wall_seconds": round(c.wall_seconds, 1), "wall_seconds_files": [c.timed_files, c.files],
                "stopped_by_time": c.stopped_by_time, "stop_not_recorded": c.stop_unknown,
                "numbers": {k: {"commits": dict(r.commits), "stopped_by_time": r.stopped_by_time}
                            for k, r in c.records.items()}}
            for d, c in columns.items()}


# -- rendering ------------------------------------------------------------------------------------
# A domain declares how it is shown (display name, scale and digits of its metric) and the paper's
# numbers for it (plad.domains.base.Domain); the report only lays them out.
def _fmt(v: float | None, digits: int) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _column(domain: str) -> tuple[str, float, int]:
    """(header, scale, digits) of a domain's metric column."""
    d = get_domain(domain)
    k = d.display_scale
    arrow = "higher is better" if d.metric.higher_is_better else "lower is better"
    name = f"{d.metric.name} x{k:g}" if k != 1 else d.metric.name
    return f"{d.display_name}: {name}, {arrow}", k, d.display_digits


def _title(domain: str) -> str:
    return get_domain(domain).display_name


def _paper(domain: str, per_round: bool = False) -> Mapping[str, float]:
    """The paper's numbers for ``domain`` (Table 1, or the supplement's per-round P_BEST), in display units."""
    d = get_domain(domain)
    return d.paper_per_round if per_round else d.paper_table


def table_markdown(results: dict[str, list[MethodResult]], methods: list[str], per_round: dict[str, str],
                   profile: str | None = None, floors: dict[str, float | None] | None = None,
                   columns: dict[str, Column] | None = None) -> str:
    """Table 1 layout: a row per method, per domain our value and the paper's; then times and P_BEST.

    ``floors`` (domain -> the floor baseline's test value) adds the row of the domains' floors (no paper value).
    ``columns`` (domain -> :class:`Column`) marks the numbers from another commit or stopped by time, with a
    note under the table when any is marked (:func:`columns_markdown` is the section that says more).
    """
    domains = list(results)
    by = {d: {r.key: r for r in rs} for d, rs in results.items()}
    lines = ["# Results" + (f" ({profile} profile)" if profile else ""), "",
             "Test sets, best of beam 10 by the domain metric. The paper's numbers (Table 1) are for reference.", ""]
    head, rule = "| method |", "|---|"
    for d in domains:
        title, _, _ = _column(d)
        head += f" {title} (ours) | paper |"
        rule += "---|---|"
    lines += [head, rule]
    for key in methods:
        row = f"| {label(key)} |"
        for d in domains:
            _, k, digits = _column(d)
            r = by[d].get(key)
            row += f" {_fmt(r.test * k if r and r.test is not None else None, digits)}{marks(columns, d, key)} |" \
                   f" {_fmt(_paper(d).get(key), digits)} |"
        lines.append(row)
    if floors and any(v is not None for v in floors.values()):
        row = f"| {floor_label(domains)} |"
        for d in domains:
            _, k, digits = _column(d)
            v = floors.get(d)
            row += f" {_fmt(v * k if v is not None else None, digits)}{marks(columns, d, FLOOR)} | — |"
        lines += [row, "", "The floor row is no method: the best program of a trivial family per test shape "
                  "(one primitive, or the tightest axis-aligned box), found without a network."]
    shown = [*methods, FLOOR, *per_round.values()]
    if any(marks(columns, d, k) for d in domains for k in shown):
        lines += ["", f"{OTHER_COMMIT}: a number from another commit than its column's; {BY_TIME}: stopped by time, "
                  f"a wall-clock limit shaped it (\"Where the numbers come from\", below)."]
    lines += ["", "## Fine-tuning runs", "",
              "| method | " + " | ".join(f"{_title(d)}: minutes, rounds (RL: epochs), training shapes, stop"
                                        for d in domains) + " |",
              "|---|" + "---|" * len(domains)]
    for key in [m for m in methods if m != "sp"] + [v for v in per_round.values() if v not in methods]:
        cells = []
        for d in domains:
            r = by[d].get(key)
            if r is None or r.train_seconds is None:
                cells.append("—")
            else:
                stop = f"{BY_TIME} stopped by time" if r.stopped_by_time else r.stopped
                shapes = "—" if r.train_shapes is None else f"{r.train_shapes:,}"
                cells.append(f"{r.train_seconds / 60:.1f} min, {r.rounds}, {shapes}, {stop}")
        lines.append(f"| {label(key)} | " + " | ".join(cells) + " |")
    if per_round:
        lines += ["", "## P_BEST: all-time vs per-round (supplement)", ""]
        for d in domains:
            _, k, digits = _column(d)
            ref, paper = _paper(d, per_round=True), _paper(d)
            lines += [f"{_title(d)}:", "",
                      "| method | all-time (ours) | per-round (ours) | all-time (paper) | per-round (paper) |",
                      "|---|---|---|---|---|"]
            for a, b in per_round.items():
                ra, rb = by[d].get(a), by[d].get(b)
                va = ra.test * k if ra and ra.test is not None else None
                vb = rb.test * k if rb and rb.test is not None else None
                lines.append(f"| {label(a)} | {_fmt(va, digits)}{marks(columns, d, a)} | "
                             f"{_fmt(vb, digits)}{marks(columns, d, b)} | "
                             f"{_fmt(paper.get(a), digits)} | {_fmt(ref.get(a), digits)} |")
            lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"


def convergence_png(results: dict[str, list[MethodResult]], path: str | Path) -> None:
    """Validation metric (best so far) against fine-tuning wall-clock time: a panel per domain, a line per method."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(1, len(results))
    fig, axes = plt.subplots(1, n, figsize=(6.5 * n, 4.5), dpi=110, squeeze=False)
    for ax, (domain, rs) in zip(axes[0], results.items()):
        metric = get_domain(domain).metric
        k = get_domain(domain).display_scale
        start = None
        for r in rs:
            if len(r.curve) < 2:
                continue
            t, v = zip(*r.curve)
            start = v[0]
            best, shown = [], None
            for x in v:   # the selected model so far, as used for the table
                shown = x if shown is None or metric.better(x, shown) else shown
                best.append(shown * k)
            ax.step([s / 60 for s in t], best, where="post", label=label(r.key), marker="o", markersize=3)
        if start is not None:
            ax.axhline(start * k, color="grey", linestyle=":", label="SP (start)")
        ax.set_xlabel("fine-tuning wall-clock time (min)")
        ax.set_ylabel(f"validation {metric.name}" + (f" x{k:g}" if k != 1 else "") + " (best so far)")
        ax.set_title(_title(domain))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write(path, lambda fh: fh.write(buf.getvalue()))


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


def _seconds(v: float | None) -> str:
    if v is None:
        return "—"
    return f"{v * 1000:.1f} ms" if v < 1 else f"{v:.2f} s"


def missing_note(missing: list[str]) -> list[str]:
    return [f"Not computed (no metrics.json): {', '.join(missing)}.", ""] if missing else []


def beyond_markdown(rows: dict[str, dict[str, Timed | None]], keys: list[str],
                    columns: dict[str, Column] | None = None) -> str:
    """The rows beyond the paper: per domain our value and seconds per shape (no paper number exists); marked as
    :func:`table_markdown` marks its numbers."""
    domains = list(rows)
    lines = ["## Beyond the paper: search beside learning", "",
             "Not in the paper: search from scratch without a network, LEST+ST+WS trained on a P_BEST seeded and "
             "rewritten by search, and the same with test-time refinement of the beam's outputs. Test sets, "
             "wall-clock seconds per shape on this machine.", ""]
    head, rule = "| method |", "|---|"
    for d in domains:
        title, _, _ = _column(d)
        head += f" {title} | s per shape |"
        rule += "---|---|"
    lines += [head, rule]
    missing = []
    for key in keys:
        row = f"| {label(key)} |"
        for d in domains:
            _, k, digits = _column(d)
            t = rows[d].get(key)
            if t is None:
                missing.append(f"{d}/{key}")
            row += f" {_fmt(t.test * k if t else None, digits)}{marks(columns, d, key) if t else ''} |" \
                   f" {_seconds(t.seconds_per_shape if t else None)} |"
        lines.append(row)
    lines.append("")
    lines += missing_note(missing)
    return "\n".join(lines)


def amortization_keys(method: str, beams: list[int]) -> list[tuple[str, str]]:
    """(result key, kind) of the amortization picture: the network at each beam, with refinement, search only."""
    return [*((eval_key(method, beam=b), "network") for b in beams),
            (eval_key(method, refine=True), "network + refinement"), (SEARCH, "search only")]


def amortization_markdown(points: dict[str, dict[str, Timed | None]], method: str, beams: list[int],
                          profile: str | None = None) -> str:
    """Metric against seconds per shape, per domain: network only (each beam), network + refinement, search only."""
    keys = amortization_keys(method, beams)
    lines = ["# Amortization: metric against seconds per shape" + (f" ({profile} profile)" if profile else ""), "",
             f"The network is {label(method)}'s model; refinement rewrites its best-of-beam program "
             f"(beam of the evaluation stage); search starts from scratch. Wall-clock seconds per shape on this "
             f"machine (a shared machine's numbers include waiting for a core).", ""]
    lines += ["\"x search\" is how many times faster than search only a configuration is (search's seconds per "
              "shape over its own).", ""]
    missing = []
    for d, got in points.items():
        title, k, digits = _column(d)
        search = got.get(SEARCH)
        lines += [f"## {_title(d)}", "",
                  f"| configuration | {title} | s per shape | x search | network | refinement |",
                  "|---|---|---|---|---|---|"]
        for key, kind in keys:
            t = got.get(key)
            if t is None:
                missing.append(f"{d}/{key}")
                continue
            faster = (f"{search.seconds_per_shape / t.seconds_per_shape:.1f}"
                      if search is not None and t.seconds_per_shape > 0 else "—")
            lines.append(f"| {label(key)} ({kind}) | {_fmt(t.test * k, digits)} | {_seconds(t.seconds_per_shape)} | "
                         f"{faster} | {_seconds(t.network_seconds_per_shape)} | "
                         f"{_seconds(t.refine_seconds_per_shape)} |")
        lines.append("")
    lines += missing_note(missing)
    return "\n".join(lines).rstrip("\n") + "\n"


def amortization_png(points: dict[str, dict[str, Timed | None]], method: str, beams: list[int],
                     path: str | Path) -> None:
    """A panel per domain: metric (y) against seconds per shape (x, log), a marker per configuration."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(1, len(points))
    fig, axes = plt.subplots(1, n, figsize=(6 * n, 4.5), dpi=110, squeeze=False)
    style = {"network": ("o", "C0"), "network + refinement": ("s", "C1"), "search only": ("^", "C2")}
    for ax, (d, got) in zip(axes[0], points.items()):
        metric, k = get_domain(d).metric, get_domain(d).display_scale
        net = [(t.seconds_per_shape, t.test * k, b) for b in beams
               if (t := got.get(eval_key(method, beam=b))) is not None]
        if net:
            ax.plot([x for x, _, _ in net], [y for _, y, _ in net], "-", color="C0", alpha=0.5)
            for x, y, b in net:
                ax.annotate(f"beam {b}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        labelled = set()
        for key, kind in amortization_keys(method, beams):
            t = got.get(key)
            if t is not None:
                marker, color = style[kind]
                name = f"{label(method)}, network only" if kind == "network" else label(key)
                ax.scatter([t.seconds_per_shape], [t.test * k], marker=marker, color=color, zorder=3,
                           label=None if name in labelled else name)
                labelled.add(name)
        ax.set_xscale("log")
        ax.set_xlabel("wall-clock seconds per shape (log)")
        ax.set_ylabel(f"test {metric.name}" + (f" x{k:g}" if k != 1 else "") +
                      (" (higher is better)" if metric.higher_is_better else " (lower is better)"))
        ax.set_title(_title(d))
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, "no results yet", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write(path, lambda fh: fh.write(buf.getvalue()))
