"""Generic, resumable MLE training of p(z|x) with early stopping.

Used by supervised pretraining and, later, by every PLAD round. An "epoch"
is a fixed number of optimizer steps (so that a checkpoint is never far
away); after each, the model is validated, the learning-rate schedule
steps, the best weights are kept, and ``last.pt`` is written atomically with
everything needed to continue: killing the process and running the same
command again resumes after the last finished epoch.
"""
from __future__ import annotations

import logging
import math
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from plad.checkpoint import read_checkpoint, save_checkpoint
from plad.model import PLADNet

log = logging.getLogger(__name__)

Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]   # shapes (N, *s), programs (N, L), lengths (N,)


@dataclass
class TrainConfig:
    batch_size: int = 128
    lr: float = 1e-3
    steps_per_epoch: int = 500
    max_epochs: int = 100
    #: epochs without an improvement of at least ``min_delta`` before stopping
    patience: int = 5
    min_delta: float = 1e-3
    #: the learning rate is multiplied by ``lr_factor`` after ``lr_patience`` epochs without improvement
    lr_patience: int = 2
    lr_factor: float = 0.5
    min_lr: float = 1e-5
    grad_clip: float = 1.0
    #: budget in minutes of training time, counted across resumes (None: no budget)
    max_minutes: float | None = None


@dataclass
class FitResult:
    best_objective: float
    best_epoch: int
    epochs: int
    stopped: str            # "patience", "max_epochs", "budget"
    seconds: float


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def fit(model: PLADNet, batches: Callable[[int], Iterator[Batch]],
        validate: Callable[[PLADNet], dict[str, float]], cfg: TrainConfig, out_dir: str | Path, *,
        domain: str, token_names: list[str], objective: str = "val_loss", higher_is_better: bool = False,
        on_epoch: Callable[[int, dict[str, float]], None] | None = None,
        loss_fn: Callable[[PLADNet, Batch], tuple[torch.Tensor, torch.Tensor]] | None = None,
        desc: str = "train", fingerprint: dict | None = None) -> FitResult:
    """Train until early stopping, ``max_epochs`` or the time budget; resume from ``out_dir/last.pt``.

    ``batches(epoch)`` yields at least ``steps_per_epoch`` batches (shapes,
    programs, lengths) on the model's device; derive them from the epoch
    number so that a resumed run sees the same data. ``validate(model)``
    returns metrics including ``objective``. The best weights are written to
    ``out_dir/best.pt`` and loaded back into ``model`` at the end.
    ``fingerprint`` identifies the run's settings: a ``last.pt`` written
    under another fingerprint is not resumed (training starts over).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sign = 1.0 if higher_is_better else -1.0
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, mode="max" if higher_is_better else "min", factor=cfg.lr_factor, patience=cfg.lr_patience,
        threshold=cfg.min_delta, threshold_mode="abs", min_lr=cfg.min_lr)
    state = {"epoch": 0, "best": -math.inf * sign, "best_epoch": 0, "bad_epochs": 0, "seconds": 0.0}
    last = out / "last.pt"
    payload = read_checkpoint(last) if last.exists() else None
    if payload is not None and payload.get("fingerprint") != fingerprint:
        log.warning("%s was written with other settings; starting over", last)
        payload = None
    if payload is not None:
        model.load_state_dict(payload["state_dict"])
        opt.load_state_dict(payload["optimizer"])
        sched.load_state_dict(payload["scheduler"])
        state.update(payload["train_state"])
        _set_rng_state(payload["rng"])
        log.info("resuming %s after epoch %d (best %.4f at epoch %d)", out, state["epoch"], state["best"],
                 state["best_epoch"])
    step_loss = loss_fn or (lambda m, b: m.loss(*b))
    budget = cfg.max_minutes * 60 if cfg.max_minutes is not None else math.inf
    stopped = "max_epochs"
    if state["bad_epochs"] >= cfg.patience:  # a resumed run that had already stopped
        stopped = "patience"
    elif state["seconds"] > budget:
        stopped = "budget"
    epochs = tqdm(range(state["epoch"], cfg.max_epochs), desc=desc, unit="epoch", initial=state["epoch"],
                  total=cfg.max_epochs, disable=None)
    for epoch in epochs if stopped == "max_epochs" else ():
        t0 = time.monotonic()
        model.train()
        total, total_acc = 0.0, 0.0
        it = batches(epoch)
        for _ in range(cfg.steps_per_epoch):
            batch = next(it)
            loss, acc = step_loss(model, batch)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            total += float(loss.detach())
            total_acc += float(acc)
        metrics = {"train_loss": total / cfg.steps_per_epoch, "train_acc": total_acc / cfg.steps_per_epoch}
        metrics.update(validate(model))
        value = metrics[objective]
        sched.step(value)
        improved = sign * (value - state["best"]) > cfg.min_delta
        state["epoch"] = epoch + 1
        if improved:
            state.update(best=value, best_epoch=epoch + 1, bad_epochs=0)
            save_checkpoint(out / "best.pt", model, domain, token_names, {"objective": value, "epoch": epoch + 1})
        else:
            state["bad_epochs"] += 1
        state["seconds"] += time.monotonic() - t0
        metrics.update(lr=opt.param_groups[0]["lr"], epoch_seconds=time.monotonic() - t0)
        save_checkpoint(last, model, domain, token_names, {
            "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "train_state": dict(state),
            "rng": _rng_state(), "fingerprint": fingerprint})
        epochs.set_postfix({objective: f"{value:.4f}", "best": f"{state['best']:.4f}"})
        if on_epoch:
            on_epoch(epoch + 1, metrics)
        if state["bad_epochs"] >= cfg.patience:
            stopped = "patience"
            break
        if state["seconds"] > budget:  # total training time, across resumes
            stopped = "budget"
            break
    best = read_checkpoint(out / "best.pt")
    model.load_state_dict(best["state_dict"])
    return FitResult(state["best"], state["best_epoch"], state["epoch"], stopped, state["seconds"])
