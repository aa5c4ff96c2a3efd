"""PLAD fine-tuning rounds (paper, Fig. 2 and Sec. 3).

One round: infer programs for every training shape with beam search and
update P_BEST; build the method's (X, Z) sources from P_BEST; train p(z|x)
by maximum likelihood on batches drawn from them, with early stopping on
the validation metric (beam ``val_beam_epoch``) and the round's best
weights restored; then validate with beam ``val_beam_round`` for model
selection across rounds. Fine-tuning stops after ``round_patience`` epochs
without a validation improvement, after ``max_rounds`` rounds, or when the
training-time budget is spent.

Everything needed to resume is on disk after each round (``state.json``,
``pbest.npz``, ``current.pt``, ``best.pt``) and within a round (the round's
``last.pt``): a killed run continues at the last finished round with the
same P_BEST.
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from plad.checkpoint import read_checkpoint, save_checkpoint
from plad.domains.base import Domain
from plad.fsutil import atomic_write_text
from plad.methods import lest_source, mixture_batches, parse_mixture, st_source
from plad.model import PLADNet
from plad.pbest import PBest
from plad.search import infer_batched
from plad.train import TrainConfig, fit

log = logging.getLogger(__name__)


@dataclass
class FinetuneConfig:
    #: a mixture of PLAD sources: st, lest, ws, e.g. "lest+st" (see plad.methods)
    method: str = "lest+st"
    pbest_mode: str = "all-time"
    infer_beam: int = 5
    infer_batch: int = 100
    val_beam_epoch: int = 3
    val_beam_round: int = 5
    #: validation shapes used (None: all)
    val_shapes: int | None = None
    max_rounds: int = 100
    #: epochs (summed over rounds) without a validation improvement before stopping
    round_patience: int = 1000
    #: minimum improvement of the validation metric that counts
    min_delta: float = 0.005
    #: training-time budget in minutes across rounds (None: none)
    max_minutes: float | None = None
    seed: int = 0
    train: TrainConfig = field(default_factory=lambda: TrainConfig(batch_size=100, lr=1e-3, steps_per_epoch=100,
                                                                    max_epochs=100, patience=10))


def mean_metric(model: PLADNet, domain: Domain, shapes: np.ndarray, beam: int, batch: int) -> float:
    return float(infer_batched(model, domain, shapes, beam, batch, desc="validate")[0].mean())


def infer_into_pbest(model: PLADNet, domain: Domain, shapes: np.ndarray, pbest: PBest, beam: int,
                     batch: int, desc: str = "infer") -> dict[str, float]:
    """Beam search over all training shapes; offer each best-of-beam program to P_BEST."""
    pbest.start_round()
    values, programs, executions = infer_batched(model, domain, shapes, beam, batch, desc=desc)
    stats = pbest.update(np.arange(len(shapes)), programs, values, executions)
    return {"pbest_mean": stats.mean, "pbest_improved": stats.improved}


def finetune(model: PLADNet, domain: Domain, train_shapes: np.ndarray, val_shapes: np.ndarray,
             cfg: FinetuneConfig, out_dir: str | Path,
             on_round: Callable[[int, dict[str, float]], None] | None = None,
             on_epoch: Callable[[int, int, dict[str, float]], None] | None = None) -> dict:
    """Fine-tune ``model`` towards ``train_shapes`` with a PLAD method; resumable from ``out_dir``."""
    mixture = parse_mixture(cfg.method)
    if "ws" in mixture.names:
        raise NotImplementedError("the wake-sleep source is not available yet")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metric = domain.metric
    sign = 1.0 if metric.higher_is_better else -1.0
    device = next(model.parameters()).device
    val = val_shapes if cfg.val_shapes is None else val_shapes[: cfg.val_shapes]
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
                 "history": [{"round": 0, f"val_{metric.name}": start_value}]}
    budget = cfg.max_minutes * 60 if cfg.max_minutes is not None else math.inf
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
        torch.manual_seed(cfg.seed * 1_000_003 + rnd)  # a resumed round draws the same dropout masks
        round_dir = out / f"round_{rnd:03d}"
        if not (round_dir / "last.pt").exists():  # P_BEST of this round not yet updated (or a fresh round)
            stats = infer_into_pbest(model, domain, train_shapes, pbest, cfg.infer_beam, cfg.infer_batch,
                                     desc=f"round {rnd} infer")
            pbest.save(out / "pbest_round.npz")
        else:
            pbest = PBest.load(out / "pbest_round.npz", metric)
            stats = {"pbest_mean": float(np.nanmean(pbest.values)), "pbest_improved": math.nan}
        sources = {"st": st_source(pbest, train_shapes, device), "lest": lest_source(pbest, device)}
        batches = mixture_batches(mixture, sources, cfg.train.batch_size, seed=cfg.seed * 7919 + rnd)

        def validate(m: PLADNet) -> dict[str, float]:
            return {f"val_{metric.name}": mean_metric(m, domain, val, cfg.val_beam_epoch, cfg.infer_batch)}

        result = fit(model, batches, validate, cfg.train, round_dir, domain=domain.name, token_names=names,
                     objective=f"val_{metric.name}", higher_is_better=metric.higher_is_better,
                     on_epoch=(lambda e, m: on_epoch(rnd, e, m)) if on_epoch else None,
                     desc=f"round {rnd} train", fingerprint={"method": cfg.method, "round": rnd})
        value = mean_metric(model, domain, val, cfg.val_beam_round, cfg.infer_batch)
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
    return {"method": cfg.method, "rounds": state["round"], "best_round": state["best_round"],
            f"val_{metric.name}": state["best"], "stopped": stopped, "train_seconds": round(state["seconds"], 1)}
