"""Stage ``finetune``: fine-tune the pretrained p(z|x) on the real training shapes with one method.

``--set key=<name>`` picks an entry of ``finetune.methods``: a PLAD mixture
(``st``, ``lest``, ``ws``, ``lest+st``, ``lest+st+ws``, with optional weights)
or ``rl`` (the REINFORCE baseline), and the P_BEST mode. The work is fixed:
the method's ``max_rounds`` (at most ``plad.max_rounds``, the default; RL:
``rl.max_epochs``) and the epochs and patience of each round; ``max_minutes``
is a wall-clock safety net, and a run it stopped (or a time limit inside a
round) is marked ``stopped_by_time`` in the summary. Every method has the
same model selection on the validation shapes. Starts from the pretrained model and the prepared shapes
and writes to ``runs/finetune/<domain>/<key>/`` (:mod:`plad.layout`):
``best.pt`` (the selected model), ``state.json`` (per-round history with
wall-clock seconds), ``summary.json`` (also copied to
``results/finetune/<domain>/<key>.json``), and the method's resumable state
(P_BEST, generator, search chunks, ...). A method with a ``search`` block seeds
and rewrites P_BEST by search (:mod:`plad.learn.pbest_search`).
A killed run, started again, resumes at its last finished round; a run folder started from
another pretrained model, other shapes or another method (``origin.json``) is started over. The PLAD
rounds are :mod:`plad.learn.rounds`, the RL baseline :mod:`plad.learn.rl`. Data-parallel
on N processes with ``torchrun --nproc-per-node N -m plad.stages.finetune ...``
(:mod:`plad.learn.distributed`); rank 0 writes the outputs and the MLflow run.
"""
from __future__ import annotations

import json
import random
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from plad.fsutil import atomic_write_text
from plad.layout import BEST, STATE, SUMMARY, Layout
from plad.learn import distributed as dist
from plad.learn.methods import MethodConfig
from plad.learn.rl import RLConfig
from plad.learn.rounds import RoundHooks, RoundsConfig
from plad.provenance import stamp
from plad.stages import StageContext, stage_main


@dataclass
class FinetuneStageConfig:
    domain: str = field(kw_only=True)
    #: which entry of ``methods`` this run trains (set per DVC stage)
    key: str | None = None
    device: str = "auto"
    #: arithmetic of the training forward passes of every method (:mod:`plad.device`): "fp32", "bf16"
    #: (autocast) or "auto" (bf16 on a CUDA GPU that computes it natively, else fp32); decoding stays float32
    precision: str = "fp32"
    threads: int | None = None
    seed: int = 0
    #: use only N training / validation shapes, evenly spaced over each split (None: all; :func:`load_shapes`)
    train_limit: int | None = None
    val_limit: int | None = None
    #: wall-clock safety net of every method, in minutes (None: none): the rounds and epochs fix the work
    max_minutes: float | None = None
    methods: dict[str, MethodConfig] = field(default_factory=dict)
    #: the PLAD rounds (every PLAD method); the P_BEST mode is each method's
    plad: RoundsConfig = field(default_factory=RoundsConfig)
    rl: RLConfig = field(default_factory=RLConfig)

    def __post_init__(self) -> None:
        from plad.device import check_precision

        check_precision(self.precision)


def method_of(cfg: FinetuneStageConfig) -> MethodConfig:
    from plad.config import ConfigError
    from plad.learn.methods import parse_mixture
    from plad.learn.pbest import MODES

    if cfg.key is None:
        raise ConfigError(f"finetune.key is not set: choose one of {', '.join(cfg.methods) or '(no methods)'}")
    if cfg.key not in cfg.methods:
        raise ConfigError(f"finetune.key {cfg.key!r} is not in finetune.methods ({', '.join(cfg.methods)})")
    m = cfg.methods[cfg.key]
    if m.method != "rl":
        try:
            parse_mixture(m.method)
        except ValueError as err:
            raise ConfigError(f"finetune.methods.{cfg.key}.method: {err}") from None
    if m.pbest_mode not in MODES:
        raise ConfigError(f"finetune.methods.{cfg.key}.pbest_mode {m.pbest_mode!r}: one of {', '.join(MODES)}")
    if m.max_rounds is not None and m.method == "rl":
        raise ConfigError(f"finetune.methods.{cfg.key}.max_rounds: RL has no rounds; its epochs are rl.max_epochs")
    if m.max_rounds is not None and m.max_rounds < 1:
        raise ConfigError(f"finetune.methods.{cfg.key}.max_rounds = {m.max_rounds}: expected at least 1")
    if m.search is not None:
        from plad.domains import get_domain
        from plad.learn.pbest_search import check

        if m.method == "rl":
            raise ConfigError(f"finetune.methods.{cfg.key}.search: RL has no P_BEST to search for")
        check(m.search, get_domain(cfg.domain), f"finetune.methods.{cfg.key}.search")
    return m


def method_params(cfg: FinetuneStageConfig) -> dict:
    """The run's params: the section with only this run's entry of ``methods`` (what its numbers depend on;
    MLflow's params and the summary's ``params_hash``)."""
    params = asdict(cfg)
    params["methods"] = {cfg.key: params["methods"][cfg.key]} if cfg.key in params["methods"] else {}
    return params


def load_shapes(cfg: FinetuneStageConfig, layout: Layout = Layout()) -> tuple[np.ndarray, np.ndarray]:
    """(training shapes, validation shapes) of the real data, limited as configured: evenly spaced over each
    split, not its first shapes (PartNet's splits are ordered by category: the first 1,000 training shapes
    are all chairs, which is what the 3D fine-tuning runs before this rule trained on)."""
    from plad.data.files import load_split

    path = layout.prepared(cfg.domain)
    return load_split(path, "train", cfg.train_limit)[0], load_split(path, "val", cfg.val_limit)[0]


#: what a fine-tuning run started from (beside ``state.json``): a run folder is resumed only if it matches
ORIGIN = "origin.json"


def run_origin(cfg: FinetuneStageConfig, spec: MethodConfig, layout: Layout) -> dict:
    """What a fine-tuning run starts from and would redo differently: the pretrained network's digest
    (:func:`plad.model.checkpoint.network_digest`) and the real shapes' sha256, the method (without its budget
    and rounds: more of either extends a run) and the shape limits.

    The run folder is a persisted DVC output (so that a killed run resumes), so DVC does not empty it when
    the pretrained model changes; this is what tells a resumable run from a stale one.
    """
    from plad.data.files import checked_sha256
    from plad.model.checkpoint import network_digest

    method = {k: v for k, v in asdict(spec).items() if k not in ("max_minutes", "max_rounds")}
    # the network, not the file's bytes: a pretraining run again writes the same weights with other seconds
    return {"model_network_sha256": network_digest(layout.model(cfg.domain)),
            "data_sha256": checked_sha256(layout.prepared(cfg.domain)),
            "method": method, "seed": cfg.seed, "train_limit": cfg.train_limit, "val_limit": cfg.val_limit,
            "subset": "evenly spaced"}


def prepare_run_dir(out: Path, origin: dict) -> None:
    """Keep ``out`` to resume if it was started from ``origin``; else empty it (saying why) and record it."""
    import shutil

    if out.exists() and any(out.iterdir()):
        path = out / ORIGIN
        old = json.loads(path.read_text()) if path.exists() else None
        if old != origin:
            what = ("it records no origin (written by an older version)" if old is None else
                    "its " + ", ".join(k for k in origin if old.get(k) != origin[k]) + " changed")
            print(f"not resuming {out}: {what}; starting over", file=sys.stderr)
            shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / ORIGIN, json.dumps(origin, indent=2, sort_keys=True) + "\n")


def finetune_stage(cfg: FinetuneStageConfig, layout: Layout = Layout(), hooks: RoundHooks | None = None) -> dict:
    """Fine-tune one method (a pure function of the config and the files it names).

    ``hooks`` (optional) run the steps of a PLAD round and hear about each
    round; for RL, ``hooks.on_unit`` hears about each epoch.
    """
    from plad.device import resolve_device, resolve_precision
    from plad.domains import get_domain
    from plad.learn.job import Job
    from plad.learn.loop import budget_seconds
    from plad.learn.rl import run_rl
    from plad.learn.rounds import run_rounds
    from plad.model.checkpoint import load_model

    started = time.monotonic()
    spec = method_of(cfg)
    hooks = hooks or RoundHooks()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    dist.init()   # under torchrun: join the other ranks (before the model goes to this rank's GPU)
    device = resolve_device(cfg.device)
    model, name = load_model(layout.model(cfg.domain), device, expect_domain=cfg.domain)
    domain = get_domain(name)
    train, val = load_shapes(cfg, layout)
    torch.manual_seed(cfg.seed)
    # Python's and NumPy's global generators: no training step draws from them, but every last.pt saves
    # their state, which must not differ between two runs of the stage
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    minutes = spec.max_minutes if spec.max_minutes is not None else cfg.max_minutes
    # the method's rounds, capped by plad.max_rounds (a profile caps every method with one key)
    rounds = cfg.plad if spec.max_rounds is None else replace(cfg.plad, max_rounds=min(spec.max_rounds,
                                                                                       cfg.plad.max_rounds))
    out = layout.finetune_dir(cfg.domain, str(cfg.key))
    if dist.is_main():   # (again, after tracked_finetune: hashing two small files is cheap)
        prepare_run_dir(out, run_origin(cfg, spec, layout))
    dist.barrier()       # no rank reads the run folder before rank 0 has kept or emptied it
    job = Job(model, domain, train, val, out, seed=cfg.seed,
              budget_seconds=budget_seconds(minutes), precision=resolve_precision(cfg.precision, device))
    if spec.method == "rl":
        summary = run_rl(job, cfg.rl, on_unit=hooks.on_unit)
    else:
        if spec.search is not None:   # P_BEST seeded and rewritten by search after each round's inference
            from plad.learn.pbest_search import PBestSearch

            hooks = replace(hooks, after_infer=PBestSearch(domain, spec.search, job.out_dir, cfg.seed).after_infer)
        summary = run_rounds(job, spec, rounds, hooks)
    work = {"max_epochs": cfg.rl.max_epochs} if spec.method == "rl" else {"max_rounds": rounds.max_rounds}
    summary = {"key": cfg.key, "domain": cfg.domain, "pbest_mode": spec.pbest_mode,
               "max_minutes": minutes, **work, **summary,
               "metric": domain.metric.name, "train_shapes": int(len(train)), "val_shapes": int(len(val)),
               "provenance": stamp(method_params(cfg), started)}
    if dist.is_main():
        text = json.dumps(summary, indent=2) + "\n"
        atomic_write_text(job.out_dir / SUMMARY, text)
        atomic_write_text(layout.finetune_summary(cfg.domain, str(cfg.key)), text)
    return summary


def tracked_finetune(cfg: FinetuneStageConfig, ctx: StageContext = StageContext(), infer=None, step=None) -> dict:
    """:func:`finetune_stage` as one MLflow run, with a nested run per round (or RL epoch)."""
    from plad.learn.loop import read_state
    from plad.model.checkpoint import read_checkpoint
    from plad.tracking import StageRun

    method_of(cfg)
    read_checkpoint(ctx.layout.model(cfg.domain))  # fail on a bad checkpoint before any MLflow run starts
    if not dist.is_main():   # one MLflow run per method, rank 0's
        return finetune_stage(cfg, ctx.layout, RoundHooks(infer=infer, step=step))
    out = ctx.layout.finetune_dir(cfg.domain, str(cfg.key))
    # before the MLflow run: a stale run folder's mlflow_run.json must not be resumed either
    prepare_run_dir(out, run_origin(cfg, method_of(cfg), ctx.layout))
    with StageRun("finetune", cfg.domain, method_params(cfg), out, method=cfg.key, params_path=ctx.params) as run:
        epochs: list[tuple[int, dict]] = []

        def on_epoch(rnd: int, epoch: int, metrics: dict) -> None:
            epochs.append((epoch, metrics))

        def on_round(rnd: int, row: dict) -> None:
            numbers = {k: float(v) for k, v in row.items() if isinstance(v, (int, float)) and np.isfinite(v)}
            run.log_metrics(numbers, step=rnd)
            # the convergence curve: validation metric against training wall-clock seconds
            run.log_metrics({"val_at_seconds": row["val"]}, step=int(round(row["seconds"])))
            with run.nested(f"round_{rnd:03d}", round=rnd) as child:
                child.log_metrics(numbers, step=rnd)
                for e, m in epochs:
                    child.log_metrics({k: float(v) for k, v in m.items() if np.isfinite(v)}, step=e)
            epochs.clear()

        summary = finetune_stage(cfg, ctx.layout,
                                 RoundHooks(infer=infer, step=step, on_unit=on_round, on_epoch=on_epoch))
        start = read_state(out / STATE).history[0]   # the pretrained model's validation metric, at 0 s
        run.log_metrics({"val_at_seconds": start["val"]}, step=0)
        run.log_metrics({k: v for k, v in summary.items() if isinstance(v, (int, float)) and not isinstance(v, bool)})
        run.set_tags({"plad.stopped": summary["stopped"], "plad.stopped_by_time": summary["stopped_by_time"]})
        from plad.domains import get_domain

        metric = get_domain(cfg.domain).metric
        run.log_result(metric=metric.name, higher_is_better=metric.higher_is_better, val=summary.get("val"),
                       train_seconds=summary.get("train_seconds"), stopped=summary["stopped"])
        for name in [SUMMARY, STATE, BEST]:
            run.log_artifact(out / name)
        final = out / ("learner.pt" if cfg.methods[cfg.key].method == "rl" else "current.pt")
        if final.exists():
            run.log_artifact(final, "final")
        # No pyfunc model per method: logging one costs seconds of environment checks per run; the
        # report logs and registers the champion of each domain (plad-<domain>@champion).
    return summary


def main(argv: list[str] | None = None) -> int:
    return stage_main("finetune", FinetuneStageConfig, tracked_finetune, argv, __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
