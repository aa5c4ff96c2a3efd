"""Stage ``search_only``: search from scratch on the real test shapes, no network (the "search, no network" row).

Runs :func:`plad.rewrite.baseline.run_baseline` (the domain's default
search configuration with ``search`` overrides, ``workers`` processes of one
thread each) on the prepared shapes of every configured split and writes to
``results/eval/search/<domain>/`` (:mod:`plad.layout`; at an effort level other than ``default``,
``results/eval/search_<effort>/<domain>/``, the report's effort rows): ``metrics.json``
(mean metric per split, seconds per shape: wall, per process and CPU; where
the numbers come from, ``provenance``, and ``stopped_by_time``) and
``<split>_programs.csv`` (index, metric value, program text per shape), the
same files as an evaluation of a network.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace

from plad.layout import METRICS, Layout, programs_csv, search_key
from plad.stages import StageContext, stage_main, write_programs_csv


@dataclass
class SearchOnlyConfig:
    domain: str = field(kw_only=True)
    splits: list[str] = field(default_factory=lambda: ["test"])
    #: only N shapes of each split, evenly spaced over it (None: all), as evaluate's limit
    limit: int | None = None
    #: worker processes (one thread each)
    workers: int = 1
    #: search configuration overrides (:func:`plad.rewrite.search_config`; {}: the domain's defaults)
    search: dict = field(default_factory=dict)
    #: effort levels searched one after another in one process, each into its own result (``search.effort`` set
    #: to each; the stages search_effort@<domain>); empty: ``search.effort`` alone
    effort_levels: list[str] = field(default_factory=list)
    #: search settings applied on top of ``search`` at every level (a trial profile's cheaper searches;
    #: params.yaml: none, so that a level is what ``plad search --effort`` runs)
    effort_overrides: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        from plad.config import ConfigError
        from plad.rewrite import EFFORTS

        effort = self.search.get("effort", "default") if isinstance(self.search, dict) else None
        if not isinstance(self.effort_overrides, dict) or "effort" in self.effort_overrides:
            raise ConfigError(f"effort_overrides = {self.effort_overrides!r}: expected a mapping of search settings "
                              f"other than effort")
        if effort not in EFFORTS:   # before any file or MLflow run is named after it
            raise ConfigError(f"search.effort = {effort!r}: expected one of {', '.join(EFFORTS)}")
        bad = [v for v in self.effort_levels if v not in EFFORTS]
        if bad:
            raise ConfigError(f"effort_levels: {bad[0]!r} is not an effort level ({', '.join(EFFORTS)})")

    def settings(self) -> dict:
        """``search`` with ``effort_overrides`` on top (a ``refine`` mapping merged key by key)."""
        merged = dict(self.search)
        for key, value in self.effort_overrides.items():
            if key == "refine" and isinstance(value, dict) and isinstance(merged.get(key), dict):
                value = {**merged[key], **value}
            merged[key] = value
        return merged

    def levels(self) -> list[SearchOnlyConfig]:
        """The configuration of each search this stage runs: one per effort level, else itself."""
        return [replace(self, search={**self.search, "effort": v}, effort_levels=[]) for v in self.effort_levels] \
            or [self]

    @property
    def key(self) -> str:
        """The result key: ``search``, or ``search_<effort>`` at an effort level other than default."""
        return search_key(self.search.get("effort", "default"))


def search_only(cfg: SearchOnlyConfig, layout: Layout = Layout()) -> dict:
    from plad.config import ConfigError
    from plad.data.files import load_split
    from plad.domains import get_domain
    from plad.fsutil import atomic_write_text
    from plad.provenance import stamp
    from plad.rewrite import search_config
    from plad.rewrite.baseline import run_baseline

    started = time.monotonic()
    domain = get_domain(cfg.domain)
    if domain.rewrite is None:
        raise ConfigError(f"search_only.{cfg.domain}: the {cfg.domain} domain has no search support")
    try:
        search_config(domain, **cfg.settings())
    except (ConfigError, TypeError) as err:
        raise ConfigError(f"search_only.{cfg.domain}.search: {err}") from None
    if cfg.workers < 1:
        raise ConfigError(f"search_only.{cfg.domain}.workers = {cfg.workers}: expected at least 1")
    out = layout.eval_dir(cfg.key, cfg.domain)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"domain": cfg.domain, "method": cfg.key, "metric": domain.metric.name,
                    "higher_is_better": domain.metric.higher_is_better, "workers": cfg.workers}
    for split in cfg.splits:
        targets, index = load_split(layout.prepared(cfg.domain), split, cfg.limit)
        s = run_baseline(cfg.domain, targets, cfg.workers, cfg.settings())
        programs, values = s.pop("programs"), s.pop("values")
        report[split] = {"mean": round(float(s["mean"]), 6), "n": s["n"], "seconds": round(s["seconds"], 1),
                         "seconds_per_shape": s["seconds_per_shape"],
                         "process_seconds_per_shape": s["process_seconds_per_shape"],
                         "cpu_seconds_per_shape": s["cpu_seconds_per_shape"], "mean_tokens": s["mean_tokens"],
                         "empty_programs": s["empty_programs"], "stats": s["stats"],
                         "stopped_by_time": s["stopped_by_time"]}
        write_programs_csv(out / programs_csv(split), domain.metric.name, index, values, programs)
        report["config"] = s["config"]
    report["stopped_by_time"] = any(report[split]["stopped_by_time"] for split in cfg.splits)
    report["provenance"] = stamp(cfg, started)
    atomic_write_text(out / METRICS, json.dumps(report, indent=2) + "\n")
    return report


def tracked_search_only(cfg: SearchOnlyConfig, ctx: StageContext = StageContext()) -> dict:
    """:func:`search_only` as an MLflow run (method ``search`` or ``search_<effort>``): the metric and seconds per
    shape per split; with ``effort_levels``, one run per level, one after another ({result key: summary})."""
    if cfg.effort_levels:
        return {c.key: _tracked_one(c, ctx) for c in cfg.levels()}
    return _tracked_one(cfg, ctx)


def _tracked_one(cfg: SearchOnlyConfig, ctx: StageContext) -> dict:
    from plad.tracking import StageRun

    out = ctx.layout.eval_dir(cfg.key, cfg.domain)
    with StageRun("search_only", cfg.domain, asdict(cfg), out, method=cfg.key, params_path=ctx.params) as run:
        report = search_only(cfg, ctx.layout)
        run.log_metrics({f"{s}_{report['metric']}": report[s]["mean"] for s in cfg.splits})
        run.log_metrics({f"{s}_seconds_per_shape": report[s]["seconds_per_shape"] for s in cfg.splits})
        test = report.get("test", {})
        run.log_result(metric=report["metric"], higher_is_better=report["higher_is_better"], test=test.get("mean"),
                       seconds_per_shape=test.get("seconds_per_shape"))
        for name in [METRICS, *[programs_csv(s) for s in cfg.splits]]:
            run.log_artifact(out / name)
    return {k: v for k, v in report.items() if k != "config"}


def main(argv: list[str] | None = None) -> int:
    return stage_main("search_only", SearchOnlyConfig, tracked_search_only, argv, __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
