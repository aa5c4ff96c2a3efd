"""Stage ``finetune``: fine-tune the pretrained p(z|x) on the real training shapes with one method.

``--set key=<name>`` picks an entry of ``finetune.methods``, whose ``method`` is a plugin of
:mod:`plad.learn.method_registry`: a PLAD mixture of sources (``st``, ``lest``, ``ws``, ``lest+st``,
``lest+st+ws``, with optional weights) or a method with its own training step (``rl``, the REINFORCE
baseline), and the P_BEST mode. The work is fixed: the method's ``max_rounds`` (at most ``plad.max_rounds``,
the default; RL: ``rl.max_epochs``) and the epochs and patience of each round; ``max_minutes`` is a
wall-clock safety net, and a run it stopped (or a time limit inside a round) is marked ``stopped_by_time``
in the summary. Every method has the same model selection on the validation shapes. Starts from the
pretrained model and the prepared shapes and writes to ``runs/finetune/<domain>/<key>/`` (:mod:`plad.layout`):
``best.pt`` (the selected model), ``state.json`` (per-round history with wall-clock seconds),
``summary.json`` (also copied to ``results/finetune/<domain>/<key>.json``), and the method's resumable state
(its last weights, P_BEST, generator, search chunks, ...). A method with a ``search`` block seeds and rewrites
P_BEST by search (:mod:`plad.learn.pbest_search`). A killed run, started again, resumes at its last finished
round; a run folder started from another pretrained model, other shapes or another method (``origin.json``)
is started over. The algorithm is :mod:`plad.learn.finetune` (one check of the method, one preparation of
the run folder); this module adds the MLflow run. Data-parallel on N processes with
``torchrun --nproc-per-node N -m plad.stages.finetune ...`` (:mod:`plad.learn.distributed`); rank 0 writes
the outputs and the MLflow run.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from plad.layout import BEST, STATE, SUMMARY, Layout
from plad.learn import distributed as dist
from plad.learn.finetune import FinetuneStageConfig, finetune, method_params, plan, prepare
from plad.learn.rounds import RoundHooks
from plad.stages import StageContext, stage_main

__all__ = ["FinetuneStageConfig", "finetune_stage", "main", "tracked_finetune"]


def finetune_stage(cfg: FinetuneStageConfig, layout: Layout = Layout(), hooks: RoundHooks | None = None) -> dict:
    """Fine-tune one method (a pure function of the config and the files it names): its one check, its run
    folder's one preparation, then :func:`plad.learn.finetune.finetune`.

    ``hooks`` (optional) run the steps of a PLAD round and hear about each
    round; for RL, ``hooks.on_unit`` hears about each epoch.
    """
    started = time.monotonic()
    run = plan(cfg)
    prepare(run, layout)
    return finetune(run, layout, hooks, started)


def tracked_finetune(cfg: FinetuneStageConfig, ctx: StageContext = StageContext(), infer=None, step=None) -> dict:
    """:func:`finetune_stage` as one MLflow run, with a nested run per round (or RL epoch)."""
    from plad.learn.loop import read_state
    from plad.model.checkpoint import read_checkpoint
    from plad.tracking import StageRun

    started = time.monotonic()
    run = plan(cfg)
    read_checkpoint(ctx.layout.model(cfg.domain))  # fail on a bad checkpoint before any MLflow run starts
    # before the MLflow run: a stale run folder's mlflow_run.json must not be resumed either
    out = prepare(run, ctx.layout)
    if not dist.is_main():   # one MLflow run per method, rank 0's
        return finetune(run, ctx.layout, RoundHooks(infer=infer, step=step), started)
    with StageRun("finetune", cfg.domain, method_params(cfg), out, method=cfg.key, params_path=ctx.params) as mlrun:
        epochs: list[tuple[int, dict]] = []

        def on_epoch(rnd: int, epoch: int, metrics: dict) -> None:
            epochs.append((epoch, metrics))

        def on_round(rnd: int, row: dict) -> None:
            numbers = {k: float(v) for k, v in row.items() if isinstance(v, (int, float)) and np.isfinite(v)}
            mlrun.log_metrics(numbers, step=rnd)
            # the convergence curve: validation metric against training wall-clock seconds
            mlrun.log_metrics({"val_at_seconds": row["val"]}, step=int(round(row["seconds"])))
            with mlrun.nested(f"round_{rnd:03d}", round=rnd) as child:
                child.log_metrics(numbers, step=rnd)
                for e, m in epochs:
                    child.log_metrics({k: float(v) for k, v in m.items() if np.isfinite(v)}, step=e)
            epochs.clear()

        summary = finetune(run, ctx.layout, RoundHooks(infer=infer, step=step, on_unit=on_round, on_epoch=on_epoch),
                           started)
        start = read_state(out / STATE).history[0]   # the pretrained model's validation metric, at 0 s
        mlrun.log_metrics({"val_at_seconds": start["val"]}, step=0)
        mlrun.log_metrics({k: v for k, v in summary.items() if isinstance(v, (int, float)) and not isinstance(v, bool)})
        mlrun.set_tags({"plad.stopped": summary["stopped"], "plad.stopped_by_time": summary["stopped_by_time"]})
        from plad.domains import get_domain

        metric = get_domain(cfg.domain).metric
        mlrun.log_result(metric=metric.name, higher_is_better=metric.higher_is_better, val=summary.get("val"),
                       train_seconds=summary.get("train_seconds"), stopped=summary["stopped"])
        for name in [SUMMARY, STATE, BEST]:
            mlrun.log_artifact(out / name)
        final = out / run.method.checkpoint   # the last weights, beside the selected best.pt
        if final.exists():
            mlrun.log_artifact(final, "final")
        # No pyfunc model per method: logging one costs seconds of environment checks per run; the
        # report logs and registers the champion of each domain (plad-<domain>@champion).
    return summary


def main(argv: list[str] | None = None) -> int:
    return stage_main("finetune", FinetuneStageConfig, tracked_finetune, argv, __doc__.splitlines()[0])


if __name__ == "__main__":
    sys.exit(main())
