"""PLAD fine-tuning rounds (paper, Fig. 2 and Sec. 3).

One round: infer programs for every training shape with beam search and
update P_BEST; build the method's (X, Z) sources from P_BEST; train p(z|x)
by maximum likelihood on batches drawn from them, with early stopping on
the validation metric (beam ``val_beam_epoch``) and the round's best
weights restored; then validate with beam ``val_beam_round`` for model
selection across rounds. Fine-tuning stops after ``round_patience`` epochs
without a validation improvement, after ``max_rounds`` rounds, or when the
training-time budget is spent.

With wake-sleep in the mixture, each round also fine-tunes the generative
model (:mod:`plad.ws`) on P_BEST and samples |S*| unique programs from it;
the generator and each round's samples are saved, so a resumed round
trains on the same data.

Inference over the training shapes goes through ``infer`` (default: one
batched beam search in this process); the Prefect flow passes a sharded,
retried version. The loop itself is the one implementation used by the DVC
stage and the flow.

Everything needed to resume is on disk after each round (``state.json``,
``pbest.npz``, ``current.pt``, ``best.pt``) and within a round (the round's
``last.pt``): a killed run continues at the last finished round with the
same P_BEST.
"""
from __future__ import annotations

import io
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from plad.checkpoint import read_checkpoint, save_checkpoint
from plad.domains.base import Domain
from plad.fsutil import atomic_write, atomic_write_text
from plad.methods import lest_source, mixture_batches, parse_mixture, st_source
from plad.model import PLADNet
from plad.pbest import PBest
from plad.search import infer_batched
from plad.train import TrainConfig, fit
from plad.ws import WSConfig, load_generator, new_generator, sample_dataset, save_generator, train_generator, ws_source

log = logging.getLogger(__name__)


@dataclass
class FinetuneConfig:
    pbest_mode: str = "all-time"
    infer_beam: int = 5
    infer_batch: int = 100
    val_beam_epoch: int = 3
    val_beam_round: int = 5
    max_rounds: int = 100
    #: epochs (summed over rounds) without a validation improvement before stopping
    round_patience: int = 1000
    #: minimum improvement of the validation metric that counts
    min_delta: float = 0.005
    train: TrainConfig = field(default_factory=lambda: TrainConfig(batch_size=100, lr=1e-3, steps_per_epoch=100,
                                                                    max_epochs=100, patience=10))
    ws: WSConfig = field(default_factory=WSConfig)


#: (model, shapes) -> (values (N,), programs (list of N token lists), executions (N, *shape))
Infer = Callable[[PLADNet, np.ndarray], tuple[np.ndarray, list, np.ndarray]]
#: step(name, fn, *args, **kwargs) -> fn(*args, **kwargs), possibly as an orchestrated task
Step = Callable[..., object]


def _direct(name: str, fn, *args, **kwargs):
    return fn(*args, **kwargs)


def mean_metric(model: PLADNet, domain: Domain, shapes: np.ndarray, beam: int, batch: int) -> float:
    return float(infer_batched(model, domain, shapes, beam, batch, desc="validate")[0].mean())


def infer_into_pbest(model: PLADNet, shapes: np.ndarray, pbest: PBest, infer: Infer) -> dict[str, float]:
    """Beam search over all training shapes; offer each best-of-beam program to P_BEST."""
    pbest.start_round()
    values, programs, executions = infer(model, shapes)
    stats = pbest.update(np.arange(len(shapes)), programs, values, executions)
    return {"pbest_mean": stats.mean, "pbest_improved": stats.improved, "infer_mean": float(np.mean(values))}


def wake_sleep_samples(model: PLADNet, domain: Domain, pbest: PBest, cfg: WSConfig, out: Path, rnd: int,
                       n: int, seed: int, max_seconds: float) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """This round's wake-sleep data: fine-tune the persistent generator on P_BEST, sample ``n`` programs."""
    device = next(model.parameters()).device
    samples = out / f"ws_round_{rnd:03d}.npz"
    if samples.exists():  # a resumed round: the same samples as before the kill
        with np.load(samples) as z:
            return z["programs"], np.unpackbits(z["executions"], axis=1, count=int(np.prod(domain.shape))) \
                .astype(bool).reshape(-1, *domain.shape), json.loads(str(z["stats"]))
    gen_file = out / "ws_generator.pt"
    gen = load_generator(gen_file, device)[0] if gen_file.exists() else new_generator(model, cfg)
    stats = train_generator(gen, pbest, cfg, seed=seed, max_seconds=max_seconds)
    save_generator(gen_file, gen, cfg, rnd)
    programs, executions, sample_stats = sample_dataset(gen, domain, n, cfg, seed=seed)
    stats.update(sample_stats)
    buf = io.BytesIO()
    np.savez_compressed(buf, programs=programs, stats=np.asarray(json.dumps(stats)),
                        executions=np.packbits(executions.reshape(len(executions), -1), axis=1))
    atomic_write(samples, lambda fh: fh.write(buf.getvalue()))
    return programs, executions, stats


def finetune(model: PLADNet, domain: Domain, train_shapes: np.ndarray, val_shapes: np.ndarray,
             method: str, cfg: FinetuneConfig, out_dir: str | Path, *, max_minutes: float | None = None,
             seed: int = 0, infer: Infer | None = None,
             on_round: Callable[[int, dict[str, float]], None] | None = None,
             on_epoch: Callable[[int, int, dict[str, float]], None] | None = None,
             step: Step | None = None) -> dict:
    """Fine-tune ``model`` towards ``train_shapes`` with the PLAD ``method`` (e.g. ``"lest+st"``).

    Resumable from ``out_dir``. ``max_minutes`` bounds the wall-clock time of
    the rounds (inference, generator, training, validation) across resumes.
    ``step(name, fn, *args)`` runs each step of a round (default: ``fn(*args)``);
    the Prefect flow makes each one a task.
    """
    run = step or _direct
    mixture = parse_mixture(method)
    if infer is None:
        def infer(m: PLADNet, shapes: np.ndarray):
            return infer_batched(m, domain, shapes, cfg.infer_beam, cfg.infer_batch, desc="infer")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metric = domain.metric
    sign = 1.0 if metric.higher_is_better else -1.0
    device = next(model.parameters()).device
    val = val_shapes
    names = domain.tokens.names

    state_file = out / "state.json"
    if state_file.exists():
        state = json.loads(state_file.read_text())
        model.load_state_dict(read_checkpoint(out / "current.pt")["state_dict"])
        pbest = PBest.load(out / "pbest.npz", metric)
        log.info("resuming %s after round %d", out, state["round"])
    else:
        pbest = PBest(len(train_shapes), domain.shape, domain.tokens.max_len, metric, cfg.pbest_mode)
        start_value = mean_metric(model, domain, val, cfg.val_beam_round, cfg.infer_batch)
        save_checkpoint(out / "best.pt", model, domain.name, names, {"round": 0, "val": start_value})
        state = {"round": 0, "best": start_value, "best_round": 0, "epochs_since_best": 0, "seconds": 0.0,
                 "history": [{"round": 0, f"val_{metric.name}": start_value, "seconds": 0.0}]}
    budget = max_minutes * 60 if max_minutes is not None else math.inf
    stopped = "max_rounds"
    while state["round"] < cfg.max_rounds:
        if state["epochs_since_best"] >= cfg.round_patience:
            stopped = "patience"
            break
        if state["seconds"] >= budget:
            stopped = "budget"
            break
        rnd = state["round"] + 1
        t0 = time.monotonic()
        torch.manual_seed(seed * 1_000_003 + rnd)  # a resumed round draws the same dropout masks
        round_dir = out / f"round_{rnd:03d}"
        if not (round_dir / "last.pt").exists():  # P_BEST of this round not yet updated (or a fresh round)
            stats = run(f"round {rnd}: infer", infer_into_pbest, model, train_shapes, pbest, infer)
            pbest.save(out / "pbest_round.npz")
        else:
            pbest = PBest.load(out / "pbest_round.npz", metric)
            stats = {"pbest_mean": float(np.nanmean(pbest.values)), "pbest_improved": math.nan}
        stats["pbest_filled"] = float(pbest.has.mean())
        sources = {"st": st_source(pbest, train_shapes, device), "lest": lest_source(pbest, device)}
        left = lambda: budget - state["seconds"] - (time.monotonic() - t0)  # noqa: E731
        if "ws" in mixture.names:
            ws_programs, ws_shapes, ws_stats = run(
                f"round {rnd}: wake-sleep generator", wake_sleep_samples, model, domain, pbest, cfg.ws, out, rnd, len(train_shapes), seed * 104_729 + rnd, left())
            stats.update(ws_stats)
            sources["ws"] = ws_source(ws_programs, ws_shapes, device)
        batches = mixture_batches(mixture, sources, cfg.train.batch_size, seed=seed * 7919 + rnd)
        train_cfg = cfg.train
        if math.isfinite(budget):
            minutes = max(left(), 0.0) / 60
            if train_cfg.max_minutes is not None:
                minutes = min(minutes, train_cfg.max_minutes)
            train_cfg = replace(train_cfg, max_minutes=minutes)

        def validate(m: PLADNet) -> dict[str, float]:
            return {f"val_{metric.name}": mean_metric(m, domain, val, cfg.val_beam_epoch, cfg.infer_batch)}

        result = run(f"round {rnd}: train", fit, model, batches, validate, train_cfg, round_dir,
                     domain=domain.name, token_names=names,
                     objective=f"val_{metric.name}", higher_is_better=metric.higher_is_better,
                     on_epoch=(lambda e, m: on_epoch(rnd, e, m)) if on_epoch else None,
                     desc=f"round {rnd} train", fingerprint={"method": method, "round": rnd})
        value = run(f"round {rnd}: validate", mean_metric, model, domain, val, cfg.val_beam_round, cfg.infer_batch)
        improved = sign * (value - state["best"]) > cfg.min_delta
        state["round"] = rnd
        state["seconds"] += time.monotonic() - t0
        if improved:
            state.update(best=value, best_round=rnd, epochs_since_best=0)
            save_checkpoint(out / "best.pt", model, domain.name, names, {"round": rnd, "val": value})
        else:
            state["epochs_since_best"] += result.epochs
        row = {"round": rnd, f"val_{metric.name}": value, **stats, "epochs": result.epochs,
               "round_seconds": time.monotonic() - t0, "seconds": state["seconds"]}
        state["history"].append(row)
        # the round is finished once all of this is on disk; state.json last
        save_checkpoint(out / "current.pt", model, domain.name, names, {"round": rnd})
        pbest.save(out / "pbest.npz")
        atomic_write_text(state_file, json.dumps(state, indent=2) + "\n")
        if on_round:
            on_round(rnd, row)
    best = read_checkpoint(out / "best.pt")
    model.load_state_dict(best["state_dict"])
    return {"method": method, "rounds": state["round"], "best_round": state["best_round"],
            f"val_{metric.name}": state["best"], "stopped": stopped, "train_seconds": round(state["seconds"], 1)}
