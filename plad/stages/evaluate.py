"""Stage ``evaluate``: best-of-beam reconstruction of real shapes with a trained p(z|x).

For every configured split: beam search (beam 10 by default), execute all
candidates, keep the best program per shape by the domain metric. The model
of ``method`` (``sp``: the pretrained one) is evaluated on the prepared
shapes; writes to ``results/eval/<method>/<domain>/`` (:mod:`plad.layout`):
``metrics.json`` (mean metric per split, with timing),
``<split>_programs.csv`` (index, metric value, program text per shape) and
``grid.png`` (target | reconstruction for a fixed, evenly spaced set of test
shapes). Evaluating ``sp`` also scores the domain's floor baseline
(:mod:`plad.eval.floor`, e.g. one box per shape) on the same shapes, into
``results/eval/floor/<domain>/`` (``metrics.json`` and the programs; a domain
without a floor gets a ``metrics.json`` saying so).

Beyond the paper (off by default, so the paper-comparable rows stay as they
are): ``refine: true`` refines each shape's best-of-beam program with the
rewriters (:func:`plad.rewrite.refine`, ``refine_config``, ``refine_workers``
processes) before scoring, into ``results/eval/<method>_refined/<domain>/``;
``refine_effort: LEVEL`` refines instead as ``plad infer --effort LEVEL`` does
(:func:`plad.eval.refinement.refinement`: at ``best`` every candidate of the beam, the best kept), into
``results/eval/<method>_refined_<LEVEL>/<domain>/`` (the report's effort rows);
``sweep_beam: k`` evaluates with beam k instead of ``beam``, into
``results/eval/<method>_beam<k>/<domain>/`` (the amortization sweep).
``metrics.json`` gives the seconds per shape of the network and of the
refinement.

Every ``metrics.json`` records where its numbers come from (``provenance``:
commit, params hash, threads, wall seconds, machine; :mod:`plad.provenance`)
and whether a wall-clock limit shaped them (``stopped_by_time``): the
training of the evaluated model (``training``, from the ``summary.json``
beside its checkpoint) or the refinement's time limit.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from plad.data.files import evenly_spaced_index, load_split
from plad.data.pictures import pair_grid, save_png
from plad.device import resolve_device
from plad.domains import get_domain
from plad.eval.floor import evaluate_floor
from plad.fsutil import atomic_write_text
from plad.layout import FLOOR, GRID, METRICS, SP, Layout, eval_key, programs_csv
from plad.model.checkpoint import load_model, read_checkpoint
from plad.model.decode import infer_batched
from plad.provenance import stamp
from plad.stages import StageContext, stage_main, write_programs_csv
from plad.tracking import StageRun


@dataclass
class EvaluateConfig:
    domain: str = field(kw_only=True)
    #: the method whose model is evaluated (a row of the results table; set per DVC stage)
    method: str = SP
    splits: list[str] = field(default_factory=lambda: ["test"])
    beam: int = 10
    batch_size: int = 100
    #: evaluate only N shapes of each split, evenly spaced over it (None: all); PartNet's splits are ordered
    #: by category, so the first N would be chairs only
    limit: int | None = None
    grid_shapes: int = 16
    device: str = "auto"
    threads: int | None = None
    #: refine each best-of-beam program before scoring (set by the evaluate_refined stages; never worse)
    refine: bool = False
    #: refine configuration overrides (:class:`plad.rewrite.RefineConfig`)
    refine_config: dict = field(default_factory=dict)
    #: refinement worker processes (one thread each)
    refine_workers: int = 1
    #: refine as ``plad infer --effort`` does at this level (fast | default | best) instead of by ``refine_config``;
    #: implies ``refine`` (set by the evaluate_effort stages)
    refine_effort: str | None = None
    #: refinement settings applied on top of ``refine_effort``'s (a trial profile's cheaper levels; params.yaml:
    #: none, so that a level is what ``plad infer --effort`` runs)
    effort_overrides: dict = field(default_factory=dict)
    #: ``refine_effort`` levels evaluated one after another in one process, each into its own result (the stages
    #: evaluate_effort@<domain>); empty: ``refine_effort`` alone
    effort_levels: list[str] = field(default_factory=list)
    #: a beam of the amortization sweep (set per beam by the evaluate_finetuned stages): used instead of ``beam``
    sweep_beam: int | None = None

    def __post_init__(self) -> None:
        # the refine settings are checked whatever ``refine`` says: a typo must not wait for the day it is used
        from plad.config import ConfigError, build
        from plad.rewrite import RefineConfig

        # ConfigError is a ValueError: params.yaml's build() names the file and section in front of it
        if not isinstance(self.refine_config, dict):
            raise ConfigError(f"refine_config = {self.refine_config!r}: expected a mapping of refine settings")
        try:
            build(RefineConfig, dict(self.refine_config), "refine_config", source="")
        except ConfigError as err:
            raise ConfigError(str(err).removeprefix(": ")) from None
        if self.refine_workers < 1:
            raise ConfigError(f"refine_workers = {self.refine_workers}: expected at least 1")
        from plad.rewrite import EFFORTS

        if self.refine_effort is not None and self.refine_effort not in EFFORTS:
            raise ConfigError(f"refine_effort = {self.refine_effort!r}: expected one of {', '.join(EFFORTS)}, "
                              f"or null (refine_config)")
        bad = [v for v in self.effort_levels if v not in EFFORTS]
        if bad:
            raise ConfigError(f"effort_levels: {bad[0]!r} is not an effort level ({', '.join(EFFORTS)})")
        if not isinstance(self.effort_overrides, dict):
            raise ConfigError(f"effort_overrides = {self.effort_overrides!r}: expected a mapping of refine settings")
        try:
            build(RefineConfig, dict(self.effort_overrides), "effort_overrides", source="")
        except ConfigError as err:
            raise ConfigError(str(err).removeprefix(": ")) from None

    def levels(self) -> list[EvaluateConfig]:
        """The configuration of each evaluation this stage runs: one per effort level, else itself."""
        return [replace(self, refine_effort=v, effort_levels=[]) for v in self.effort_levels] or [self]


def result_key(cfg: EvaluateConfig) -> str:
    """Where this evaluation's results go (:func:`plad.layout.eval_key`)."""
    return eval_key(cfg.method, cfg.sweep_beam, cfg.refine, cfg.refine_effort)


def _write_programs(path, domain, values: np.ndarray, programs: list[list[int]], index: np.ndarray) -> None:
    write_programs_csv(path, domain.metric.name, index, values, [domain.format(p) for p in programs])


def training_record(checkpoint) -> dict | None:
    """How the evaluated model's training ended, from the run summary beside its checkpoint (None: none there):
    its loop's unit, units, stop reason and whether a wall-clock limit shaped it."""
    from plad.layout import SUMMARY

    path = checkpoint.parent / SUMMARY
    try:
        s = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(s, dict) or "stopped" not in s:
        return None
    # summaries written before the flag: the loop's budget stop was the only wall-clock limit they knew
    timed = s.get("stopped_by_time", s.get("stopped") == "budget")
    units = next((s[k] for k in ("units", "rounds", "epochs") if k in s), None)   # older summaries' names
    return {"unit_name": s.get("unit_name"), "units": units, "stopped": s.get("stopped"),
            "stopped_by_time": bool(timed), "commit": (s.get("provenance") or {}).get("commit")}


def evaluate_floor_splits(cfg: EvaluateConfig, domain, layout: Layout) -> dict:
    """The domain's floor baseline on the configured splits: ``results/eval/floor/<domain>/``."""
    started = time.monotonic()
    out = layout.eval_dir(FLOOR, cfg.domain)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"domain": cfg.domain, "method": FLOOR, "floor": domain.floor_name or None,
                    "metric": domain.metric.name, "higher_is_better": domain.metric.higher_is_better}
    for split in cfg.splits if domain.floor_name else []:
        targets, index = load_split(layout.prepared(cfg.domain), split, cfg.limit)
        start = time.monotonic()
        values, programs = evaluate_floor(domain, targets)
        report[split] = {"mean": round(float(values.mean()), 6), "n": int(len(values)),
                         "seconds": round(time.monotonic() - start, 1)}
        _write_programs(out / programs_csv(split), domain, values, programs, index)
    report["stopped_by_time"] = False
    report["provenance"] = stamp(cfg, started)
    atomic_write_text(out / METRICS, json.dumps(report, indent=2) + "\n")
    return report


def evaluate(cfg: EvaluateConfig, layout: Layout = Layout()) -> dict:
    from plad.config import ConfigError

    started = time.monotonic()

    refine = cfg.refine or cfg.refine_effort is not None
    if refine:   # refine_config and refine_workers are checked with the config (EvaluateConfig.__post_init__)
        from plad.rewrite.pool import refine_all
    beam = cfg.beam if cfg.sweep_beam is None else cfg.sweep_beam
    if beam < 1:
        raise ConfigError(f"evaluate: beam {beam} must be at least 1")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    device = resolve_device(cfg.device)
    checkpoint = layout.model(cfg.domain, cfg.method)
    model, name = load_model(checkpoint, device, expect_domain=cfg.domain)
    domain = get_domain(name)
    out = layout.eval_dir(result_key(cfg), cfg.domain)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"domain": cfg.domain, "method": cfg.method, "metric": domain.metric.name,
                    "higher_is_better": domain.metric.higher_is_better, "beam": beam, "refine": refine,
                    "checkpoint": str(checkpoint)}
    how = None
    if cfg.refine_effort is not None:
        from plad.eval.refinement import refinement

        how = refinement(domain, cfg.refine_effort)
        if cfg.effort_overrides:
            from plad.rewrite.pool import refine_config

            how = replace(how, config=refine_config({**asdict(how.config), **cfg.effort_overrides}))
        report.update(refine_effort=cfg.refine_effort, refine_all_candidates=how.all_candidates,
                      refine_config=asdict(how.config))
    training = training_record(checkpoint)
    refine_timed = False
    for split in cfg.splits:
        targets, index = load_split(layout.prepared(cfg.domain), split, cfg.limit)
        start = time.monotonic()
        desc = f"{cfg.method} {split} beam {beam}"
        if how is None:
            values, programs, shapes = infer_batched(model, domain, targets, beam, cfg.batch_size, desc=desc)
            starts, owner = programs, list(range(len(programs)))
        else:
            from plad.eval.refinement import infer_starts

            values, programs, shapes, starts, owner = infer_starts(model, domain, targets, beam, cfg.batch_size,
                                                                   how.all_candidates, desc=desc)
        network = time.monotonic() - start
        n = max(len(values), 1)
        row = {"mean": round(float(values.mean()), 6), "n": int(len(values))}
        if refine:
            row["network_mean"] = row["mean"]
            overrides = cfg.refine_config if how is None else asdict(how.config)
            aims = targets if how is None else targets[owner]   # (len(starts), *shape): each start's target
            refined, values, shapes, timed = refine_all(domain.name, starts, aims, overrides, cfg.refine_workers)
            if how is not None:   # each shape's best refined start (its best-of-beam program's on ties)
                from plad.eval.refinement import keep_best

                chosen = keep_best(domain.metric.better, len(programs), owner, values)
                refined, values, shapes = [refined[k] for k in chosen], values[chosen], shapes[chosen]
                row["refined_starts"] = len(starts)
            programs = refined
            row["mean"] = round(float(values.mean()), 6)
            row["refine_stopped_by_time"] = timed
            refine_timed |= timed
        seconds = time.monotonic() - start
        row.update(seconds=round(seconds, 1), shapes_per_second=round(len(values) / max(seconds, 1e-9), 2),
                   seconds_per_shape=seconds / n, network_seconds_per_shape=network / n,
                   refine_seconds_per_shape=(seconds - network) / n)
        report[split] = row
        _write_programs(out / programs_csv(split), domain, values, programs, index)
        if split == cfg.splits[-1]:
            # a fixed, evenly spaced set of the shapes (the same for every method)
            idx = evenly_spaced_index(len(targets), cfg.grid_shapes)
            save_png(pair_grid(targets[idx], shapes[idx]), out / GRID)
    report["training"] = training
    report["stopped_by_time"] = bool(refine_timed or (training or {}).get("stopped_by_time"))
    report["provenance"] = stamp(cfg, started)
    atomic_write_text(out / METRICS, json.dumps(report, indent=2) + "\n")
    if cfg.method == SP and not refine and cfg.sweep_beam is None:  # the floor is evaluate@<d>'s output
        report[FLOOR] = evaluate_floor_splits(cfg, domain, layout)
    return report


def tracked_evaluate(cfg: EvaluateConfig, ctx: StageContext = StageContext()) -> dict:
    """:func:`evaluate` as an MLflow run: the metric per split and the outputs as artifacts; with
    ``effort_levels``, one run per level, one after another ({result key: report})."""
    if cfg.effort_levels:
        return {result_key(c): _tracked_one(c, ctx) for c in cfg.levels()}
    return _tracked_one(cfg, ctx)


def _tracked_one(cfg: EvaluateConfig, ctx: StageContext) -> dict:
    read_checkpoint(ctx.layout.model(cfg.domain, cfg.method))  # a missing or bad checkpoint fails before MLflow
    out = ctx.layout.eval_dir(result_key(cfg), cfg.domain)
    with StageRun("evaluate", cfg.domain, asdict(cfg), out, method=result_key(cfg), params_path=ctx.params) as run:
        report = evaluate(cfg, ctx.layout)
        run.log_metrics({f"{s}_{report['metric']}": report[s]["mean"] for s in cfg.splits})
        run.log_metrics({f"{s}_seconds_per_shape": report[s]["seconds_per_shape"] for s in cfg.splits})
        floor = report.get(FLOOR, {})
        run.log_metrics({f"floor_{s}_{report['metric']}": floor[s]["mean"] for s in cfg.splits if s in floor})
        # the row of this result (and of the floor) at MLflow's top level (plad.tracking.rows)
        kind = {"metric": report["metric"], "higher_is_better": report["higher_is_better"]}
        test = report.get("test", {})
        run.log_result(**kind, test=test.get("mean"), seconds_per_shape=test.get("seconds_per_shape"))
        if "test" in floor:
            run.log_result(method=FLOOR, **kind, test=floor["test"]["mean"])
        for name in [METRICS, GRID, *[programs_csv(s) for s in cfg.splits]]:
            run.log_artifact(out / name)
    return report


def main(argv: list[str] | None = None) -> int:
    return stage_main("evaluate", EvaluateConfig, tracked_evaluate, argv, __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
