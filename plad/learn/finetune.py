"""Fine-tuning one method of the comparison: the algorithm of stage ``finetune`` (:mod:`plad.stages.finetune`).

:func:`plan` checks the run once: its entry of ``finetune.methods`` (the key) and the method that entry
names, a plugin of :mod:`plad.learn.method_registry` (a PLAD mixture, trained by :mod:`plad.learn.rounds`,
or a method with its own training step, such as RL, :mod:`plad.learn.rl`). :func:`prepare` keeps or
empties the run folder once (``origin.json``: a run folder started from another pretrained model, other
shapes or another method is started over, not resumed). :func:`finetune` loads the pretrained model and
the shapes, runs the method and writes ``summary.json``. The stage's outputs are described there.
"""
from __future__ import annotations

import json
import random
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from plad.config import ConfigError
from plad.fsutil import atomic_write_text
from plad.layout import SUMMARY, Layout
from plad.learn import distributed as dist
from plad.learn.method_registry import Method, get_method
from plad.learn.methods import MethodConfig
from plad.learn.rl import RLConfig
from plad.learn.rounds import RoundHooks, RoundsConfig
from plad.provenance import stamp


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


@dataclass(frozen=True)
class Plan:
    """A checked fine-tuning run: the stage's config, its entry of ``methods`` and the method that trains it."""

    cfg: FinetuneStageConfig
    spec: MethodConfig
    method: Method


def plan(cfg: FinetuneStageConfig) -> Plan:
    """The one check of the run's method: its key, its entry and what the entry's method says of it
    (:meth:`Method.check`); a ``ConfigError`` naming the key otherwise."""
    from plad.learn.pbest import MODES

    if cfg.key is None:
        raise ConfigError(f"finetune.key is not set: choose one of {', '.join(cfg.methods) or '(no methods)'}")
    if cfg.key not in cfg.methods:
        raise ConfigError(f"finetune.key {cfg.key!r} is not in finetune.methods ({', '.join(cfg.methods)})")
    spec, where = cfg.methods[cfg.key], f"finetune.methods.{cfg.key}"
    try:
        method = get_method(spec.method)
    except ValueError as err:
        raise ConfigError(f"{where}.method: {err}") from None
    if spec.pbest_mode not in MODES:
        raise ConfigError(f"{where}.pbest_mode {spec.pbest_mode!r}: one of {', '.join(MODES)}")
    try:
        method.check(spec, cfg, where)
    except ConfigError:
        raise
    except ValueError as err:
        raise ConfigError(str(err)) from None
    return Plan(cfg, spec, method)


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


def prepare(run: Plan, layout: Layout = Layout()) -> Path:
    """The run folder, prepared once for every rank: rank 0 keeps it to resume or empties it
    (:func:`prepare_run_dir`); no rank goes on before rank 0 has done so."""
    dist.init()   # under torchrun: join the other ranks (before the model goes to this rank's GPU)
    out = layout.finetune_dir(run.cfg.domain, str(run.cfg.key))
    if dist.is_main():
        prepare_run_dir(out, run_origin(run.cfg, run.spec, layout))
    dist.barrier()
    return out


def finetune(run: Plan, layout: Layout = Layout(), hooks: RoundHooks | None = None,
             started: float | None = None) -> dict:
    """Fine-tune with the method of ``run`` in its prepared run folder (:func:`prepare`); returns the summary,
    also written (rank 0) to ``summary.json`` and the results folder.

    ``hooks`` (optional) run the steps of a PLAD round and hear about each unit (a round; RL: an epoch).
    ``started`` (``time.monotonic()``) is when the stage started, for the summary's provenance.
    """
    from plad.device import resolve_device, resolve_precision
    from plad.domains import get_domain
    from plad.learn.job import Job
    from plad.learn.loop import budget_seconds
    from plad.model.checkpoint import load_model

    started = time.monotonic() if started is None else started
    cfg, spec, method = run.cfg, run.spec, run.method
    hooks = hooks or RoundHooks()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
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
    job = Job(model, domain, train, val, layout.finetune_dir(cfg.domain, str(cfg.key)), seed=cfg.seed,
              budget_seconds=budget_seconds(minutes), precision=resolve_precision(cfg.precision, device))
    summary = method.run(job, spec, cfg, hooks)
    summary = {"key": cfg.key, "domain": cfg.domain, "pbest_mode": spec.pbest_mode,
               "max_minutes": minutes, **method.work(spec, cfg), **summary,
               "metric": domain.metric.name, "train_shapes": int(len(train)), "val_shapes": int(len(val)),
               "provenance": stamp(method_params(cfg), started)}
    if dist.is_main():
        text = json.dumps(summary, indent=2) + "\n"
        atomic_write_text(job.out_dir / SUMMARY, text)
        atomic_write_text(layout.finetune_summary(cfg.domain, str(cfg.key)), text)
    return summary
