"""Stage ``report``: ``results/table.md``, ``results/convergence.png``, the amortization picture, the MLflow champion.

The table has the paper's Table 1 layout (one row per method, SP first) with
the paper's numbers beside ours, and the supplement's P_BEST all-time vs
per-round comparison. ``source: mlflow`` rebuilds the same report from the
MLflow store alone.

Only when asked (``--register`` on the command line, as dvc.yaml's report
stage does, or ``register: true``) is the model with the best validation
metric (over SP and every fine-tuned method; a method's value is the best of
its validation history) registered as ``plad-<domain>`` with the
``champion`` alias, and only if that value beats the current champion's
(recorded as its version's ``plad.val`` tag), by the metric's direction
(:attr:`plad.metrics.Metric.higher_is_better`). Each decision is printed.

Beyond the paper (``beyond``, from the evaluation files whatever the
source): a table of rows with search and their seconds per shape, appended
to ``table.md``, with search and the ``amortization.method``'s network +
refinement at each effort level of ``efforts.table``;
``results/amortization.md`` and ``.png``: metric against seconds per shape
for the ``amortization.method``'s model at each of ``beams``, with test-time
refinement, and search only, and both of these at each of ``efforts.levels``
(also ``report.json``'s ``efforts`` per domain). Missing inputs of these are
named in the files, not errors.

The MLflow run of the report is nested under the profile's pipeline run
(:mod:`plad.tracking.rows`), which gets ``table.md``, ``convergence.png``,
``amortization.png`` (and ``amortization.md``, ``report.json``) as its own
artifacts; and every row of the tables gets its numbers on its row run
(``report.json``'s ``rows``: test and validation metric, seconds per shape,
training seconds, stop reason), so that MLflow's top level holds the same
numbers as ``table.md`` even where DVC skipped a stage whose output was cached.

Where each column's numbers come from (from the files' ``provenance``
blocks, whatever the source: :func:`plad.eval.report.column`): the last
section of ``table.md`` gives each column's commit, the numbers from another commit,
the stages' wall time and the numbers a wall-clock limit shaped (stopped by
time), and the tables mark those numbers; ``report.json`` holds the same
under ``columns``, and its own ``provenance``.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace

from plad.config import ConfigError
from plad.data.files import DataError
from plad.domains import get_domain
from plad.eval.report import (
    MethodResult,
    Timed,
    amortization_keys,
    amortization_markdown,
    amortization_png,
    beyond_markdown,
    column,
    columns_json,
    columns_markdown,
    convergence_png,
    floor_from_files,
    floor_from_mlflow,
    from_files,
    from_mlflow,
    table_markdown,
    timed_from_files,
)
from plad.fsutil import atomic_write_text
from plad.layout import (
    AMORTIZATION_PLOT,
    AMORTIZATION_TABLE,
    CONVERGENCE,
    FLOOR,
    REPORT,
    SP,
    SUMMARY,
    TABLE,
    Layout,
    eval_key,
    search_key,
)
from plad.provenance import stamp
from plad.stages import StageContext, stage_main
from plad.tracking import StageRun, champion_tags, set_champion, set_version_tags, tracking_uri
from plad.tracking.registry import model_name
from plad.tracking.rows import PIPELINE, runs_path


@dataclass
class AmortizationConfig:
    #: the method whose model the evaluate_refined stages and evaluate_finetuned's beam sweep evaluate
    method: str = "lest_st_ws_search"


@dataclass
class EffortsConfig:
    """The effort levels of search and of network + refinement in the report (issue 56): ``levels`` in
    ``report.json`` and the amortization picture and table (the whole curve), ``table`` as rows of ``table.md``."""

    levels: list[str] = field(default_factory=list)
    table: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        from plad.layout import EFFORT_LEVELS

        for name in ("levels", "table"):
            bad = [v for v in getattr(self, name) if v not in EFFORT_LEVELS]
            if bad:
                raise ValueError(f"{name}: {bad[0]!r} is not an effort level ({', '.join(EFFORT_LEVELS)})")
        if not set(self.table) <= set(self.levels):
            raise ValueError(f"table {self.table}: every level of the table must be one of levels {self.levels}")


@dataclass
class ReportConfig:
    #: the table's columns
    domains: list[str] = field(kw_only=True)
    #: rows of the table, in order (keys of finetune.methods, plus "sp")
    methods: list[str] = field(default_factory=lambda: ["sp", "rl", "ws", "st", "lest", "lest_st", "lest_st_ws"])
    #: all-time method key -> its per-round variant, for the P_BEST comparison
    per_round: dict[str, str] = field(default_factory=lambda: {"lest_st": "lest_st_per_round"})
    #: where the numbers come from: "files" (the pipeline's outputs) or "mlflow"
    source: str = "files"
    #: register the best model (by validation) in the MLflow registry with alias "champion", if it beats the
    #: current champion; off unless asked (the command line's --register sets it)
    register: bool = False
    profile: str | None = None
    #: rows beyond the paper, by result key (``search``, a method, ``<method>_refined``), in their own table
    beyond: list[str] = field(default_factory=list)
    amortization: AmortizationConfig = field(default_factory=AmortizationConfig)
    #: effort levels of search (stages search_only, search_effort) and of the amortization method's network +
    #: refinement (stages evaluate_effort)
    efforts: EffortsConfig = field(default_factory=EffortsConfig)
    #: the beams of the amortization sweep (the top-level ``beams``)
    beams: list[int] = field(default_factory=lambda: [1, 5, 10])

    def __post_init__(self) -> None:
        # the typed loader checks the containers, not their items: result keys are looked up and hashed
        for name in ("methods", "beyond"):
            bad = [k for k in getattr(self, name) if not isinstance(k, str)]
            if bad:
                raise ValueError(f"{name}: {bad[0]!r} is not a result key (a method name)")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in self.per_round.items()):
            raise ValueError(f"per_round {self.per_round!r}: expected method name -> method name")
        if not all(isinstance(b, int) and not isinstance(b, bool) and b >= 1 for b in self.beams):
            raise ValueError(f"beams {self.beams!r}: expected positive integers")


def gather(cfg: ReportConfig, layout: Layout = Layout()) -> dict:
    """{domain: [MethodResult per method]} from the configured source."""
    keys = list(dict.fromkeys([*cfg.methods, *cfg.per_round.values()]))
    if cfg.source == "files":
        return {d: from_files(d, keys, layout) for d in cfg.domains}
    if cfg.source == "mlflow":
        return {d: from_mlflow(d, keys) for d in cfg.domains}
    raise ConfigError(f"report.source {cfg.source!r}: expected files or mlflow")


def champion(cfg: ReportConfig, domain: str, results) -> tuple[str, float] | None:
    """(method key, validation value) of the selected model with the best validation metric.

    SP competes with its own validation value, the first point of every curve.
    """
    metric = get_domain(domain).metric
    candidates = []
    for r in results:
        if r.key in cfg.per_round.values():
            continue
        if r.curve:
            candidates.append((SP, r.curve[0][1]))
        if r.val_best is not None and r.key != SP:
            candidates.append((r.key, r.val_best))
    best = None
    for key, v in candidates:
        if best is None or metric.better(v, best[1]):
            best = (key, v)
    return best


def gather_complete(cfg: ReportConfig, layout: Layout = Layout()) -> dict:
    """:func:`gather`, or a :class:`DataError` naming every method and domain without a test evaluation."""
    results = gather(cfg, layout)
    missing = [f"{d}/{r.key}" for d, rs in results.items() for r in rs if r.test is None]
    if missing:
        where = "MLflow" if cfg.source == "mlflow" else layout.results_dir
        raise DataError(where, f"no test evaluation for {', '.join(missing)}")
    return results


def _pretrain_summary(domain: str, layout: Layout) -> dict:
    """SP's training: ``runs/pretrain/<domain>/summary.json`` ({} when absent, e.g. a report from MLflow alone)."""
    path = layout.pretrain_dir(domain) / SUMMARY
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def result_rows(results: list[MethodResult], floor: float | None, timed: dict[str, Timed | None],
                pretrain: dict) -> dict[str, dict]:
    """One domain's rows of the tables as MLflow's top level shows them: {result key: {test, val,
    seconds_per_shape, train_seconds, stopped}} (only the values known).

    SP's validation value is the first point of the fine-tuning curves (the pretrained model, as
    :func:`champion` counts it), its training that of pretraining; the floor's is its test value alone.
    """
    def known(**values) -> dict:
        return {k: v for k, v in values.items() if v is not None}

    start = next((r.curve[0][1] for r in results if r.curve), None)
    # all of pretraining when it continued another run (its segments' total), else this run's
    pretrain_seconds = pretrain.get("totals", {}).get("train_seconds", pretrain.get("train_seconds"))
    rows: dict[str, dict] = {}
    for r in results:
        t = timed.get(r.key)
        if r.key == SP:
            rows[r.key] = known(test=r.test, val=start, seconds_per_shape=t.seconds_per_shape if t else None,
                                train_seconds=pretrain_seconds, stopped=pretrain.get("stopped"))
        else:
            rows[r.key] = known(test=r.test, val=r.val_best, seconds_per_shape=t.seconds_per_shape if t else None,
                                train_seconds=r.train_seconds, stopped=r.stopped)
    for key, t in timed.items():
        if key not in rows and t is not None:
            rows[key] = {"test": t.test, "seconds_per_shape": t.seconds_per_shape}
    if floor is not None:
        rows[FLOOR] = {"test": floor}
    return rows


def report(cfg: ReportConfig, layout: Layout = Layout()) -> dict:
    started = time.monotonic()
    results = gather_complete(cfg, layout)
    out = layout.results_dir
    out.mkdir(parents=True, exist_ok=True)
    if cfg.source == "mlflow":
        floors = {d: floor_from_mlflow(d) for d in cfg.domains}
    else:
        floors = {d: floor_from_files(d, layout) for d in cfg.domains}
    method, levels = cfg.amortization.method, cfg.efforts.levels
    keys = [k for k, _ in amortization_keys(method, cfg.beams, levels)]
    # the rows beyond the paper, then search and network + refinement at each effort level of the table
    beyond_keys = list(dict.fromkeys([*cfg.beyond, *(k for lv in cfg.efforts.table
                                                    for k in (search_key(lv), eval_key(method, effort=lv)))]))
    shown = list(dict.fromkeys([*cfg.methods, *cfg.per_round.values(), *beyond_keys, *keys]))
    columns = {d: column(d, shown, layout) for d in cfg.domains}
    table = table_markdown(results, cfg.methods, cfg.per_round, cfg.profile, floors, columns)
    beyond = {d: timed_from_files(d, beyond_keys, layout) for d in cfg.domains}
    if beyond_keys:
        table += "\n" + beyond_markdown(beyond, beyond_keys, columns)
    table += "\n" + columns_markdown(columns, [*cfg.methods, *cfg.per_round.values(), *beyond_keys])
    atomic_write_text(out / TABLE, table)
    points = {d: timed_from_files(d, keys, layout) for d in cfg.domains}
    atomic_write_text(out / AMORTIZATION_TABLE, amortization_markdown(points, method, cfg.beams, cfg.profile, levels))
    amortization_png(points, method, cfg.beams, out / AMORTIZATION_PLOT, levels)
    convergence_png({d: [r for r in rs if r.key not in cfg.per_round.values()] for d, rs in results.items()},
                    out / CONVERGENCE)
    summary: dict = {"source": cfg.source, "domains": {}}
    where = columns_json(columns)
    for d, rs in results.items():
        timed = timed_from_files(d, list(dict.fromkeys([r.key for r in rs] + beyond_keys + keys)), layout)
        entry = {"test": {r.key: r.test for r in rs}, "train_seconds": {r.key: r.train_seconds for r in rs},
                 "stopped_by_time": {r.key: r.stopped_by_time for r in rs}, "floor": floors[d],
                 "column": where[d], "rows": result_rows(rs, floors[d], timed, _pretrain_summary(d, layout))}
        best = champion(cfg, d, rs)
        if best is not None:
            entry["champion"] = {"method": best[0], "val": best[1]}
        entry["beyond"] = {k: (vars(t) if t else None) for k, t in beyond[d].items()}
        entry["amortization"] = {k: (vars(t) if t else None) for k, t in points[d].items()}
        # per effort level, least work first: search and network + refinement (None: not computed)
        entry["efforts"] = {lv: {kind: (vars(t) if (t := points[d].get(k)) else None)
                                 for kind, k in (("search", search_key(lv)),
                                                 ("network + refinement", eval_key(method, effort=lv)))}
                            for lv in levels}
        summary["domains"][d] = entry
    summary["provenance"] = stamp(cfg, started)
    atomic_write_text(out / REPORT, json.dumps(summary, indent=2) + "\n")
    return summary


def tracked_report(cfg: ReportConfig, ctx: StageContext = StageContext()) -> dict:
    """:func:`report` as an MLflow run; registers each domain's champion as ``plad-<domain>@champion``."""
    out = ctx.layout.results_dir
    if cfg.source == "files":
        gather_complete(cfg, ctx.layout)   # missing evaluations fail before an MLflow run (or store) exists
    with StageRun("report", ",".join(cfg.domains), asdict(cfg), out / ".report_run", params_path=ctx.params,
                  row=PIPELINE) as run:
        summary = report(cfg, ctx.layout)
        for name in [TABLE, CONVERGENCE, REPORT, AMORTIZATION_TABLE, AMORTIZATION_PLOT]:
            run.log_artifact(out / name)
            run.log_row_artifact(out / name)
        for d, entry in summary["domains"].items():
            metric = get_domain(d).metric
            for key, values in entry["rows"].items():
                run.log_result(domain=d, method=key, metric=metric.name, higher_is_better=metric.higher_is_better,
                               **values)
        if cfg.register:
            for d, entry in summary["domains"].items():
                if "champion" not in entry:
                    print(f"report: plad-{d}: no validated model; nothing registered", file=sys.stderr)
                    continue
                key, val = entry["champion"]["method"], entry["champion"]["val"]
                # a trial profile's models live under a name of their own (plad-<domain>-smoke): never the default
                name = model_name(f"plad-{d}")
                metric = get_domain(d).metric
                checkpoint = ctx.layout.model(d, key)
                if not checkpoint.exists():
                    # a column rebuilt on this machine beside others whose results are committed but whose
                    # checkpoints (uncommitted run outputs) were made elsewhere: report them, register nothing
                    entry["champion"]["registered"] = False
                    print(f"report: plad-{d}: its best model, {key}, has no checkpoint here ({checkpoint}); "
                          f"nothing registered", file=sys.stderr)
                    continue
                current = champion_tags(name)
                held = _recorded_val(current)
                if held is not None and not metric.better(val, held):
                    # the store's champion stays: say which one it is, so report.json still names the model
                    entry["champion"].update(registered=False, held={
                        "model": f"models:/{name}@champion", "version": str(current[0]), "val": held})
                    print(f"report: kept {name}@champion (version {current[0]}, validation {metric.name} {held:.6g}):"
                          f" the best here, {key} with {val:.6g}, does not beat it", file=sys.stderr)
                    continue
                version = run.log_model(checkpoint, registered_name=name).rsplit("/", 1)[-1]
                set_version_tags(name, version, {"plad.method": key, "plad.test": entry["test"].get(key),
                                                 "plad.val": repr(float(val)), "plad.metric": metric.name})
                set_champion(name, version)
                entry["champion"].update(model=f"models:/{name}@champion", version=version, registered=True)
                was = "" if current is None else (f", replacing version {current[0]}" + (
                    f" ({held:.6g})" if held is not None else " (no recorded validation value)"))
                print(f"report: registered {name} version {version} ({key}, validation {metric.name} {val:.6g}) "
                      f"as {name}@champion{was}", file=sys.stderr)
            atomic_write_text(out / REPORT, json.dumps(summary, indent=2) + "\n")
            run.log_row_artifact(out / REPORT)   # with the champions
        # each domain's experiment is its comparison (one metric per experiment); its runs page, without the
        # GenAI/Model training switch (MLflow 3.17 opens an experiment on GenAI until switched)
        pages = ", ".join(f"{d} http://127.0.0.1:5000/{runs_path(run.experiment_of(d))}" for d in cfg.domains)
        print(f"report: MLflow: `mlflow ui --backend-store-uri {tracking_uri()}`, then Model training > "
              f"plad-<domain> ({pages})", file=sys.stderr)
    return summary


def _recorded_val(champion: tuple[int, dict[str, str]] | None) -> float | None:
    """The validation value a champion version was registered with (its ``plad.val`` tag), if any."""
    if champion is None:
        return None
    try:
        return float(champion[1]["plad.val"])
    except (KeyError, ValueError):
        return None


def _options(parser):
    parser.add_argument("--register", action="store_true",
                        help="register each domain's best model as plad-<domain>@champion if it beats the current "
                             "champion's validation value (otherwise nothing is registered)")
    return lambda cfg, args: replace(cfg, register=True) if args.register else cfg


def main(argv: list[str] | None = None) -> int:
    return stage_main("report", ReportConfig, tracked_report, argv, __doc__.splitlines()[0], options=_options)

if __name__ == "__main__":
    sys.exit(main())
