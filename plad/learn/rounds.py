"""PLAD fine-tuning rounds (paper, Fig. 2 and Sec. 3).

One round: infer programs for every training shape with beam search and
update P_BEST; build the method's (X, Z) sources from P_BEST; train p(z|x)
by maximum likelihood on batches drawn from them, with early stopping on
the validation metric (beam ``val_beam_epoch``) and the round's best
weights restored; then validate with beam ``val_beam_round`` for model
selection across rounds. Fine-tuning stops after ``round_patience`` epochs
without a validation improvement, after ``max_rounds`` rounds, or when the
training-time budget (a safety net: the profiles fix the rounds) is spent.

With wake-sleep in the mixture, each round also fine-tunes the generative
model (:mod:`plad.learn.ws`) on P_BEST and samples |S*| unique programs from it;
the generator and each round's samples are saved, so a resumed round
trains on the same data.

Inference over the training shapes goes through ``infer`` (default: one
batched beam search in this process); the Prefect flow passes a sharded,
retried version. The loop itself is the one implementation used by the DVC
stage and the flow.

A hook (:attr:`RoundHooks.after_infer`) may change P_BEST after the
inference and before the training of each round: a method with search
seeds and rewrites it there (:mod:`plad.learn.pbest_search`).

Everything needed to resume is on disk after each round (``state.json``,
``pbest.npz``, ``current.pt``, ``best.pt``) and within a round (the round's
``last.pt``): a killed run continues at the last finished round with the
same P_BEST. The loop over rounds (patience, budget, selection, history) is
:class:`plad.learn.loop.Loop`, as for every other trainer.

Under torchrun (:mod:`plad.learn.distributed`) the ranks split the beam inference
over the training and validation shapes and gather the results, so every
rank holds the same P_BEST; training is data-parallel (:func:`plad.learn.train.fit`,
:func:`plad.learn.ws.train_generator`), each rank drawing its own batches from the
sources; rank 0 alone writes files and samples the wake-sleep programs.
"""
from __future__ import annotations

import io
import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from plad.device import FP32, Precision
from plad.domains.base import Domain
from plad.fsutil import atomic_write, atomic_write_text, savez
from plad.layout import BEST, LAST, STATE
from plad.learn import distributed as dist
from plad.learn.job import Job
from plad.learn.loop import JsonStore, Limits, Loop, Objective, Unit
from plad.learn.method_registry import PairSource, get_source
from plad.learn.methods import MethodConfig, RoundContext, mixture_batches, parse_mixture
from plad.learn.pbest import PBest
from plad.learn.train import FitSetup, TrainConfig, fit
from plad.learn.ws import (
    WSConfig,
    load_generator,
    new_generator,
    sample_dataset,
    save_generator,
    train_generator,
    ws_source,
)
from plad.model.checkpoint import read_checkpoint, save_checkpoint
from plad.model.decode import infer_batched
from plad.model.network import PLADNet

log = logging.getLogger(__name__)


@dataclass
class RoundsConfig:
    """Settings of the PLAD rounds (params ``finetune.<domain>.plad``); the P_BEST mode is the method's."""

    infer_beam: int = 5
    infer_batch: int = 100
    val_beam_epoch: int = 3
    val_beam_round: int = 5
    max_rounds: int = 100
    #: epochs (summed over rounds) without a validation improvement before stopping
    round_patience: int = 1000
    #: minimum improvement of the validation metric that counts
    min_delta: float = 0.005
    train: TrainConfig = field(default_factory=TrainConfig)
    ws: WSConfig = field(default_factory=WSConfig)


#: columns of a round's history that say a time limit cut a step of it short (wake-sleep generator, search)
TIMED_COLUMNS = ("ws_stopped_by_time", "seed_stopped_by_time", "rewrite_stopped_by_time")

#: (model, shapes) -> (values (N,), programs (list of N token lists), executions (N, *shape))
Infer = Callable[[PLADNet, np.ndarray], tuple[np.ndarray, list, np.ndarray]]
#: step(name, fn, *args, **kwargs) -> fn(*args, **kwargs), possibly as an orchestrated task
Step = Callable[..., object]


def _direct(name: str, fn, *args, **kwargs):
    return fn(*args, **kwargs)


def mean_metric(model: PLADNet, domain: Domain, shapes: np.ndarray, beam: int, batch: int) -> float:
    """Mean best-of-beam metric over ``shapes`` (the shapes split across the ranks of a distributed run)."""
    parts = dist.map_split(lambda idx: infer_batched(model, domain, shapes[idx], beam, batch, desc="validate")[0],
                           len(shapes))
    return float(np.concatenate(parts).mean())


def split_across_ranks(infer: Infer, shape: tuple[int, ...]) -> Infer:
    """``infer`` with the shapes split across the ranks of a distributed run and the results gathered on every
    rank (``infer`` itself in one process). Executions travel bit-packed."""
    if dist.world() == 1:
        return infer
    size = int(np.prod(shape))

    def part(model: PLADNet, shapes: np.ndarray):
        values, programs, executions = infer(model, shapes)
        return values, programs, np.packbits(executions.reshape(len(shapes), size), axis=1)

    def split(model: PLADNet, shapes: np.ndarray):
        parts = dist.map_split(lambda idx: part(model, shapes[idx]), len(shapes))
        executions = np.concatenate([np.unpackbits(p[2], axis=1, count=size) for p in parts]).astype(bool)
        return (np.concatenate([p[0] for p in parts]), [z for p in parts for z in p[1]],
                executions.reshape(-1, *shape))
    return split


def infer_into_pbest(model: PLADNet, shapes: np.ndarray, pbest: PBest, infer: Infer) -> dict[str, float]:
    """Beam search over all training shapes; offer each best-of-beam program to P_BEST."""
    pbest.start_round()
    values, programs, executions = infer(model, shapes)
    stats = pbest.update(np.arange(len(shapes)), programs, values, executions)
    return {"pbest_mean": stats.mean, "pbest_improved": stats.improved, "infer_mean": float(np.mean(values))}


def wake_sleep_samples(model: PLADNet, domain: Domain, pbest: PBest, cfg: WSConfig, out: Path, rnd: int,
                       n: int, seed: int, max_seconds: float,
                       precision: Precision = FP32) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """This round's wake-sleep data: fine-tune the persistent generator on P_BEST, sample ``n`` programs."""
    device = next(model.parameters()).device
    samples = out / f"ws_round_{rnd:03d}.npz"

    def read(source) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
        with np.load(source) as z:
            return z["programs"], np.unpackbits(z["executions"], axis=1, count=int(np.prod(domain.shape))) \
                .astype(bool).reshape(-1, *domain.shape), json.loads(str(z["stats"]))

    if dist.broadcast(samples.exists()):  # a resumed round: the same samples as before the kill
        return read(samples)
    gen_file = out / "ws_generator.pt"
    gen = load_generator(gen_file, device)[0] if dist.broadcast(gen_file.exists()) else new_generator(model, cfg)
    stats = train_generator(gen, pbest, cfg, seed=seed, max_seconds=max_seconds, precision=precision)
    if not dist.is_main():   # rank 0 samples; the others get the very file it wrote
        return read(io.BytesIO(dist.broadcast(None)))
    save_generator(gen_file, gen, cfg, rnd)
    programs, executions, sample_stats = sample_dataset(gen, domain, n, cfg, seed=seed)
    stats.update(sample_stats)
    buf = io.BytesIO()
    savez(buf, programs=programs, stats=np.asarray(json.dumps(stats)),
                        executions=np.packbits(executions.reshape(len(executions), -1), axis=1))
    atomic_write(samples, lambda fh: fh.write(buf.getvalue()))
    dist.broadcast(buf.getvalue())
    return programs, executions, stats


@dataclass
class RoundHooks:
    """How the steps of a round run and who hears about them (all optional)."""

    #: inference over the training shapes (default: one batched beam search in this process)
    infer: Infer | None = None
    #: ``step(name, fn, *args)`` runs each step of a round (default: ``fn(*args)``); the Prefect flow makes tasks
    step: Step | None = None
    #: ``on_unit(round, row)`` after each finished round, with its history row
    on_unit: Callable[[int, dict[str, Any]], None] | None = None
    #: ``on_epoch(round, epoch, row)`` after each training epoch inside a round
    on_epoch: Callable[[int, int, dict[str, Any]], None] | None = None
    #: ``after_infer(round, pbest, train_shapes)`` after each round's inference, before its training: may
    #: change P_BEST in place (e.g. :mod:`plad.learn.pbest_search`); returns columns for the round's history row
    after_infer: Callable[[int, PBest, np.ndarray], dict[str, float]] | None = None


def run_rounds(job: Job, method: MethodConfig, cfg: RoundsConfig, hooks: RoundHooks | None = None) -> dict:
    """Fine-tune ``job.model`` towards ``job.train`` with the PLAD ``method`` (e.g. ``lest+st``, all-time P_BEST).

    Resumable from ``job.out_dir``. ``job.budget_seconds`` bounds the wall-clock
    time of the rounds (inference, generator, training, validation) across
    resumes. Returns the run summary (:meth:`plad.learn.loop.LoopResult.summary`).
    """
    hooks = hooks or RoundHooks()
    run = hooks.step or _direct
    mixture = parse_mixture(method.method)
    model, domain, out = job.model, job.domain, job.out_dir
    infer = hooks.infer
    if infer is None:
        def infer(m: PLADNet, shapes: np.ndarray):
            return infer_batched(m, domain, shapes, cfg.infer_beam, cfg.infer_batch, desc="infer")
        infer = split_across_ranks(infer, tuple(domain.shape))
    out.mkdir(parents=True, exist_ok=True)
    metric = domain.metric
    device = next(model.parameters()).device
    names = domain.tokens.names
    pbest = PBest(len(job.train), domain.shape, domain.tokens.max_len, metric, method.pbest_mode,
                  canonical=domain.canonical)

    def restore() -> None:
        nonlocal pbest
        model.load_state_dict(read_checkpoint(out / "current.pt")["state_dict"])
        pbest = PBest.load(out / "pbest.npz", metric, domain.canonical)

    def save(unit: int, folder: Path) -> None:   # staged, then moved to out/ by the store's commit
        save_checkpoint(folder / "current.pt", model, domain.name, names, {"unit": unit})
        pbest.save(folder / "pbest.npz")

    def validate_round() -> float:
        return mean_metric(model, domain, job.val, cfg.val_beam_round, cfg.infer_batch)

    def keep_best(unit: int, value: float) -> None:
        if dist.is_main():
            save_checkpoint(out / BEST, model, domain.name, names, {"unit": unit, "val": value})

    def restore_best() -> None:
        model.load_state_dict(read_checkpoint(out / BEST)["state_dict"])

    def validate_epoch(m: PLADNet) -> dict[str, float]:
        return {"val": mean_metric(m, domain, job.val, cfg.val_beam_epoch, cfg.infer_batch)}

    def one_round(rnd: int, remaining: Callable[[], float]) -> Unit:
        nonlocal pbest
        torch.manual_seed(job.seed * 1_000_003 + rnd)  # a resumed round draws the same dropout masks
        round_dir = out / f"round_{rnd:03d}"
        if not dist.broadcast((round_dir / LAST).exists()):  # P_BEST of this round not yet updated
            stats = run(f"round {rnd}: infer", infer_into_pbest, model, job.train, pbest, infer)
            if hooks.after_infer is not None:
                stats.update(run(f"round {rnd}: search", hooks.after_infer, rnd, pbest, job.train))
                stats["pbest_mean"] = float(np.nanmean(pbest.values))
            if dist.is_main():
                pbest.save(out / "pbest_round.npz")
                # what the resumed round must still report: whether a search step ran out of time
                atomic_write_text(out / "pbest_round.json",
                                  json.dumps({k: stats[k] for k in TIMED_COLUMNS if k in stats}) + "\n")
        else:
            pbest = PBest.load(out / "pbest_round.npz", metric, domain.canonical)
            stats = {"pbest_mean": float(np.nanmean(pbest.values)), "pbest_improved": math.nan}
            if (out / "pbest_round.json").exists():
                stats.update(json.loads((out / "pbest_round.json").read_text()))
        stats["pbest_filled"] = float(pbest.has.mean())
        ctx = RoundContext(job, cfg, pbest, rnd, device, remaining, run)
        sources = {}
        for name in mixture.names:   # each source of the mixture, from its plugin (method_registry)
            sources[name], columns = get_source(name).build(ctx)
            stats.update(columns)
        batches = mixture_batches(mixture, sources, cfg.train.batch_size, seed=dist.rank_seed(job.seed * 7919 + rnd),
                                  bucket_pool=cfg.train.bucket_pool)
        # the round trains within what is left of the run's budget
        setup = FitSetup(domain.name, names, objective=Objective("val", metric.higher_is_better),
                         budget_seconds=remaining(),
                         on_unit=(lambda e, row: hooks.on_epoch(rnd, e, row)) if hooks.on_epoch else None,
                         desc=f"round {rnd} train", fingerprint={"method": method.method, "round": rnd, **(
                             {"near_smoothing": cfg.train.near_smoothing} if cfg.train.near_smoothing else {})},
                         precision=job.precision)
        result = run(f"round {rnd}: train", fit, model, batches, validate_epoch, cfg.train, round_dir, setup)
        value = run(f"round {rnd}: validate", mean_metric, model, domain, job.val, cfg.val_beam_round,
                    cfg.infer_batch)
        # a time limit inside the round (the training's or the generator's share of the budget, a search step's)
        timed = result.stopped_by_time or any(stats.get(k) for k in TIMED_COLUMNS)
        # patience counts training epochs, so that it means the same whatever the epochs per round
        return Unit(value, {**stats, "epochs": result.units}, patience=result.units, stopped_by_time=bool(timed))

    loop = Loop("round", metric, Limits(cfg.max_rounds, cfg.round_patience, cfg.min_delta, job.budget_seconds),
                JsonStore(out / STATE, save=save, restore=restore))
    result = loop.run(one_round, start=validate_round, keep_best=keep_best, restore_best=restore_best,
                      on_unit=hooks.on_unit)
    return {"method": method.method, **result.summary()}


class _WSSource(PairSource):
    """Wake-sleep: this round's samples of the generator fine-tuned on P_BEST (:func:`wake_sleep_samples`)."""

    def build(self, ctx: RoundContext):
        job = ctx.job
        programs, shapes, stats = ctx.step(
            f"round {ctx.rnd}: wake-sleep generator", wake_sleep_samples, job.model, job.domain, ctx.pbest,
            ctx.cfg.ws, job.out_dir, ctx.rnd, len(job.train), job.seed * 104_729 + ctx.rnd, ctx.remaining(),
            job.precision)
        return ws_source(programs, shapes, ctx.device), stats


#: the registered ``ws`` source (:mod:`plad.learn.method_registry`)
WS = _WSSource()
