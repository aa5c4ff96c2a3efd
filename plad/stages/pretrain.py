"""Stage ``pretrain``: supervised pretraining of p(z|x) on synthetic (shape, program) pairs, as an MLflow run.

The algorithm is :func:`plad.learn.pretrain.pretrain` (see there: outputs in ``runs/pretrain/<domain>/``,
resumable, per-epoch diagnostics). Data-parallel on N processes with ``torchrun --nproc-per-node N -m
plad.stages.pretrain ...`` (:mod:`plad.learn.distributed`). The stage adds to ``summary.json`` where its
numbers come from (``provenance``: commit, params hash, threads, wall seconds, machine; :mod:`plad.provenance`).
"""
from __future__ import annotations

import json
import random
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from plad.config import ConfigError
from plad.fsutil import atomic_write_text
from plad.layout import BEST, HISTORY, PROVENANCE, SUMMARY, Layout
from plad.learn import distributed as dist
from plad.learn.pretrain import PretrainConfig, check_epochs, pretrain
from plad.learn.synthetic import load_programs
from plad.provenance import stamp
from plad.stages import StageContext, stage_main


def resolve_init(cfg: PretrainConfig, layout) -> Path | None:
    """The checkpoint ``cfg.init`` names: ``"shipped"`` is the domain's shipped pretrained network (verified
    against its index), a path is relative to the layout root."""
    if cfg.init is None:
        return None
    if cfg.init == "shipped":
        from plad.shipped import ShipError, pretrained_checkpoint

        try:
            return pretrained_checkpoint(cfg.domain)
        except ShipError as err:
            raise ConfigError(f"pretrain.{cfg.domain}.init: {err}") from None
    return Path(cfg.init) if Path(cfg.init).is_absolute() else layout.root / cfg.init


def with_provenance(cfg: PretrainConfig, summary: dict, started: float, layout: Layout) -> dict:
    """``summary`` with its ``provenance`` block, written again to ``summary.json`` (rank 0)."""
    summary = {**summary, "provenance": stamp(cfg, started)}
    if dist.is_main():
        atomic_write_text(layout.pretrain_dir(cfg.domain) / SUMMARY, json.dumps(summary, indent=2) + "\n")
    return summary


def tracked_pretrain(cfg: PretrainConfig, ctx: StageContext = StageContext()) -> dict:
    """:func:`pretrain` as an MLflow run: per-epoch metrics, outputs and the model."""
    from plad.tracking import StageRun

    started = time.monotonic()
    load_programs(ctx.layout.synthetic(cfg.domain))  # fail before any MLflow run starts
    # Python's and NumPy's global generators: no training step draws from them, but last.pt saves their
    # state, which must not differ between two runs of the stage
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    init = resolve_init(cfg, ctx.layout)
    check_epochs(cfg, init)
    if init is not None:   # the checkpoint to continue is checked before any MLflow run starts, too
        from plad.domains import get_domain
        from plad.learn.pretrain import read_init
        from plad.model.network import ModelConfig

        read_init(init, cfg, ModelConfig.for_domain(cfg.model, get_domain(cfg.domain)))
    if not dist.is_main():   # one MLflow run per training, rank 0's
        return pretrain(cfg, ctx.layout, init_path=init)
    out = ctx.layout.pretrain_dir(cfg.domain)
    with StageRun("pretrain", cfg.domain, asdict(cfg), out, params_path=ctx.params) as run:
        summary = pretrain(cfg, ctx.layout, on_epoch=lambda e, m: run.log_metrics(m, step=e), init_path=init)
        summary = with_provenance(cfg, summary, started, ctx.layout)
        run.log_metrics({f"final_{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
        run.log_metrics({f"total_{k}": float(v) for k, v in summary.get("totals", {}).items()
                         if isinstance(v, (int, float))})
        # SP's row: its training, all segments of it when it continues another (its validation metric on the
        # real shapes is the fine-tuning curves' start)
        run.log_result(train_seconds=summary.get("totals", {}).get("train_seconds", summary.get("train_seconds")),
                       stopped=summary.get("stopped"))
        run.log_artifact(out / SUMMARY)
        run.log_artifact(out / HISTORY)
        if (out / PROVENANCE).exists():
            run.log_artifact(out / PROVENANCE)
        run.log_artifact(out / BEST, "checkpoint")
        run.log_model(out / BEST)
    return summary



def main(argv: list[str] | None = None) -> int:
    return stage_main("pretrain", PretrainConfig, tracked_pretrain, argv, __doc__.splitlines()[0])

if __name__ == "__main__":
    sys.exit(main())
