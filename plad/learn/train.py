"""Generic, resumable MLE training of p(z|x) with early stopping.

Used by supervised pretraining and, inside every round, by the PLAD methods.
An "epoch" is a fixed number of optimizer steps (so that a checkpoint is
never far away); after each, the model is validated, the learning-rate
schedule steps, the best weights are kept, and ``last.pt`` is written
atomically with everything needed to continue: killing the process and
running the same command again resumes after the last finished epoch. The
loop itself (stopping, budget, best, history) is :class:`plad.learn.loop.Loop`.

Under torchrun (:mod:`plad.learn.distributed`) every rank runs :func:`fit` on its
own batches with the gradients averaged (DDP); rank 0's validation metrics
drive the schedule and the loop, and only rank 0 writes ``last.pt`` and
``best.pt``. Each rank's random stream (dropout) is re-seeded at every
epoch from (seed, epoch, rank), so a resumed run needs no per-rank state.
"""
from __future__ import annotations

import logging
import math
import random
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from plad.device import FP32, Precision
from plad.layout import BEST, LAST
from plad.learn import distributed as dist
from plad.learn.loop import Limits, Loop, LoopResult, LoopState, Objective, Unit, upgrade_state
from plad.learn.state import check_training_state
from plad.model.checkpoint import CheckpointError, read_checkpoint, save_checkpoint
from plad.model.network import PLADNet

log = logging.getLogger(__name__)

Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]   # shapes (N, *s), programs (N, L), lengths (N,)

#: pretraining selects on the validation loss
VAL_LOSS = Objective("val_loss", higher_is_better=False)


@dataclass
class TrainConfig:
    """One epoch-based MLE training loop. The only set of defaults: profiles set every key.

    There is no budget here: a run has one budget knob (``pretrain.max_minutes``,
    ``finetune.max_minutes``), and a PLAD round trains within what is left of it.
    """

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
    #: batches drawn together and grouped by program length (:mod:`plad.data.batching`); 1: plain random batches
    bucket_pool: int = 1
    #: linear learning-rate warm-up from lr / warmup_steps to lr over the first steps (0: none); the
    #: plateau schedule starts once it is over. Early large steps let the decoder settle on the programs'
    #: statistics before the encoder's signal arrives (issue 14)
    warmup_steps: int = 0
    #: a near miss costs less than a far one: the share of each target token's probability spread over the
    #: tokens one grid step from it (numeric parameters; :func:`plad.domains.grammar.near_targets`, issue 58);
    #: 0: plain cross-entropy, the loss of every run before it
    near_smoothing: float = 0.0

    def __post_init__(self) -> None:   # ValueError: plad.config.build names the file and the key
        if not 0.0 <= self.near_smoothing < 1.0:
            raise ValueError(f"near_smoothing {self.near_smoothing}: expected 0 <= near_smoothing < 1")


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    # a checkpoint holds plain data only (plad.model.checkpoint.plain): NumPy's key array comes back as a tensor
    name, keys, *rest = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), *rest))
    random.setstate(state["python"])


class Stages(Protocol):
    """A training schedule in stages that :func:`fit` consults and checkpoints
    (:class:`plad.learn.curriculum.Curriculum`).

    Until ``final``, the loop's patience does not run and the plateau schedule does not reduce the learning
    rate. ``end_epoch(steps, metrics)`` runs on every rank with rank 0's metrics and returns extra history
    columns; the state is part of ``last.pt``.
    """

    @property
    def final(self) -> bool: ...

    def end_epoch(self, steps: int, metrics: dict[str, float]) -> dict[str, float]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


@dataclass
class Init:
    """Where a continued training starts: another run's ``last.pt`` payload (weights, optimizer, schedule,
    RNGs, stages and loop state), continued as a new segment (:meth:`plad.learn.loop.LoopState.new_segment`).

    ``restart_lr``: the learning rate goes back to ``lr`` with the warm-up of :class:`TrainConfig` counted
    from the segment's first step, and the plateau schedule starts afresh; otherwise the saved schedule
    continues, and the segment trains exactly as the run it continues would have gone on.
    """

    payload: dict[str, Any]
    objective: Objective
    restart_lr: bool = False
    lr: float = 1e-3


def _same_work(payload: dict[str, Any], fingerprint: dict | None) -> bool:
    """Whether a ``last.pt`` payload was written by the work ``fingerprint`` names (else :func:`fit` starts over)."""
    return payload.get("fingerprint") == fingerprint


def resumes(last: Path, fingerprint: dict | None) -> bool:
    """Whether :func:`fit` will continue ``last`` rather than start over (a damaged file: fit refuses it in its
    own words, so it counts as continued here)."""
    if not last.exists():
        return False
    try:
        return _same_work(read_checkpoint(last), fingerprint)
    except CheckpointError:
        return True


class _LastCheckpoint:
    """The loop's store for :func:`fit`: weights, optimizer, schedule, RNGs and loop state in one atomic ``last.pt``."""

    def __init__(self, path: Path, model: PLADNet, opt, sched, domain: str, token_names: list[str],
                 fingerprint: dict | None, stages: Stages | None = None, init: Init | None = None,
                 extra: Callable[[dict[str, Any]], dict[str, Any]] | None = None):
        self.path, self.model, self.opt, self.sched = path, model, opt, sched
        self.domain, self.token_names, self.fingerprint = domain, token_names, fingerprint
        self.stages, self.init, self.extra = stages, init, extra
        #: units done before this segment (set by load; 0 for a fresh run)
        self.segment_unit = 0

    def load(self) -> dict[str, Any] | None:
        payload = read_checkpoint(self.path) if self.path.exists() else None
        if payload is not None and not _same_work(payload, self.fingerprint):
            log.warning("%s was written with other settings; starting over", self.path)
            payload = None
        if payload is not None:   # a damaged state is refused in one line (CheckpointError), never resumed
            check_training_state(self.path, payload)
        if payload is None and self.init is not None:
            return self._start_segment()
        if payload is None:
            return None
        state = self._restore(payload)
        self.segment_unit = int(state.get("segment_unit", 0))
        return state

    def _start_segment(self) -> dict[str, Any]:
        """Continue another run's state (``init``) as a new segment of this one."""
        state = LoopState.from_dict(self._restore(self.init.payload), "epoch").new_segment(self.init.objective)
        self.segment_unit = state.segment_unit
        if self.init.restart_lr:   # a rate a plateau rule drove to its floor is not resumed; Adam's moments are
            for group in self.opt.param_groups:
                group["lr"] = self.init.lr
            fresh = type(self.sched)(self.opt, mode=self.sched.mode, factor=self.sched.factor,
                                     patience=self.sched.patience, threshold=self.sched.threshold,
                                     threshold_mode=self.sched.threshold_mode, min_lr=self.sched.min_lrs)
            self.sched.load_state_dict(fresh.state_dict())
        return state.to_dict()

    def _restore(self, payload: dict[str, Any]) -> dict[str, Any]:
        self.model.load_state_dict(payload["state_dict"])
        self.opt.load_state_dict(payload["optimizer"])
        # the plateau rule's settings are this run's configuration, which a resume may change as it may change
        # the budget (a saved state_dict carries them and would silently keep the old ones); its state (the
        # best value, the epochs without improvement) comes from the checkpoint
        settings = {k: getattr(self.sched, k) for k in ("factor", "patience", "threshold", "threshold_mode",
                                                          "min_lrs", "eps")}
        self.sched.load_state_dict(payload["scheduler"])
        for key, value in settings.items():
            setattr(self.sched, key, value)
        _set_rng_state(payload["rng"])
        if self.stages is not None and payload.get("stages") is not None:
            self.stages.load_state_dict(payload["stages"])
        # "train_state": a last.pt written before plad.learn.loop (same meaning, other key names)
        return payload["loop"] if "loop" in payload else upgrade_state(payload["train_state"], "epoch")

    def commit(self, state: dict[str, Any]) -> None:
        save_checkpoint(self.path, self.model, self.domain, self.token_names, {
            "optimizer": self.opt.state_dict(), "scheduler": self.sched.state_dict(), "loop": state,
            "rng": _rng_state(), "fingerprint": self.fingerprint,
            "stages": self.stages.state_dict() if self.stages is not None else None,
            **(self.extra(state) if self.extra is not None else {})})


@dataclass
class FitSetup:
    """What :func:`fit` is told besides the model, its data and :class:`TrainConfig`: the network's names
    for its checkpoints and the run's optional hooks.

    ``budget_seconds`` counts training time across resumes. ``on_unit(epoch, row)`` gets each epoch's
    history row (train and validation metrics, ``lr``). ``loss_fn(model, batch)``: the (loss, accuracy)
    trained on (default: the model's own loss). ``desc``: the progress line's label. ``fingerprint``
    identifies the run's settings: a ``last.pt`` written under another fingerprint is not resumed.
    ``stages`` (e.g. a curriculum, which ``batches`` reads) is told each epoch's metrics and saved with
    ``last.pt``; see :class:`Stages`. ``init``: when ``out_dir`` holds no ``last.pt`` of this run, start
    from another run's state as a new segment (see :class:`Init`); ``max_epochs`` and the budget then count
    this segment's epochs and time. ``extra(loop_state)`` returns more keys for ``last.pt`` (e.g.
    provenance). ``precision`` is the arithmetic of the training forward passes (:func:`train_step`);
    validation is ``validate``'s own.
    """

    domain: str
    token_names: list[str]
    objective: Objective = VAL_LOSS
    budget_seconds: float = math.inf
    on_unit: Callable[[int, dict[str, Any]], None] | None = None
    loss_fn: Callable[[PLADNet, Batch], tuple[torch.Tensor, torch.Tensor]] | None = None
    desc: str = "train"
    fingerprint: dict | None = None
    stages: Stages | None = None
    init: Init | None = None
    extra: Callable[[dict[str, Any]], dict[str, Any]] | None = None
    precision: Precision = FP32


#: a batch's (loss, accuracy), e.g. the model's loss through :func:`plad.learn.distributed.data_parallel`
StepLoss = Callable[[Batch], tuple[torch.Tensor, torch.Tensor]]


def train_step(model: PLADNet, opt: torch.optim.Optimizer, step_loss: StepLoss, batch: Batch,
               grad_clip: float | None, precision: Precision = FP32) -> tuple[torch.Tensor, torch.Tensor]:
    """One optimizer step on ``batch``: the loss's forward pass under ``precision`` (:mod:`plad.device`),
    backward, gradient-norm clip, update. Returns the (loss, accuracy) tensors, detached: reading them as
    numbers waits for a GPU, so a caller sums them as tensors and reads them once in a while."""
    with precision.autocast():
        loss, acc = step_loss(batch)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip:
        torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    opt.step()
    return loss.detach(), acc.detach()


def _own_loss(model: PLADNet, domain: str, near_smoothing: float) -> Callable[[PLADNet, Batch], Any]:
    """The model's own loss, against :func:`plad.domains.grammar.near_targets` when ``near_smoothing`` > 0."""
    if not near_smoothing:
        return lambda m, b: m.loss(*b)
    from plad.domains import get_domain
    from plad.domains.grammar import near_targets

    soft = near_targets(get_domain(domain).tokens.tokens, near_smoothing).to(next(model.parameters()).device)
    return lambda m, b: m.loss(*b, soft=soft)


def fit(model: PLADNet, batches: Callable[[int], Iterator[Batch]],
        validate: Callable[[PLADNet], dict[str, float]], cfg: TrainConfig, out_dir: str | Path,
        setup: FitSetup) -> LoopResult:
    """Train until early stopping, ``max_epochs`` or the time budget; resume from ``out_dir/last.pt``.

    ``batches(epoch)`` yields at least ``steps_per_epoch`` batches (shapes,
    programs, lengths) on the model's device; derive them from the epoch
    number so that a resumed run sees the same data (in a distributed run:
    this rank's part, see :mod:`plad.learn.distributed`). ``validate(model)``
    returns metrics including ``setup.objective.name``, the value selected on; it
    runs on every rank (it may split its work across them). The
    best weights are written to ``out_dir/best.pt`` and loaded back into
    ``model`` at the end. ``setup`` (:class:`FitSetup`) names the run and holds its optional hooks.
    """
    domain, token_names, objective = setup.domain, setup.token_names, setup.objective
    stages, init, precision = setup.stages, setup.init, setup.precision
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, mode="max" if objective.higher_is_better else "min", factor=cfg.lr_factor, patience=cfg.lr_patience,
        threshold=cfg.min_delta, threshold_mode="abs", min_lr=cfg.min_lr)
    step_loss = dist.data_parallel(model, setup.loss_fn or _own_loss(model, domain, cfg.near_smoothing))
    seed = torch.initial_seed()   # the caller's seed, before a resume restores the RNG state

    def epoch(unit: int, remaining: Callable[[], float]) -> Unit:
        model.train()
        if dist.world() > 1:   # this rank's dropout stream, fixed by (seed, epoch, rank): nothing per rank to save
            torch.manual_seed(dist.rank_seed(seed * 1_000_003 + unit))
        # float64 sums on the model's device: the same additions as summing Python floats, without waiting for
        # the GPU at every step
        device = next(model.parameters()).device
        total = torch.zeros((), dtype=torch.float64, device=device)
        total_acc = torch.zeros((), dtype=torch.float64, device=device)
        it = batches(unit - 1)   # batch streams are numbered from 0
        for i in range(cfg.steps_per_epoch):
            # the warm-up counts from the first step of the run, or of the segment when it restarts the rate
            first = store.segment_unit if init is not None and init.restart_lr else 0
            step = (unit - 1 - first) * cfg.steps_per_epoch + i
            if step < cfg.warmup_steps:   # linear warm-up; the plateau schedule takes over after it
                for group in opt.param_groups:
                    group["lr"] = cfg.lr * (step + 1) / cfg.warmup_steps
            loss, acc = train_step(model, opt, step_loss, next(it), cfg.grad_clip, precision)
            total += loss.double()
            total_acc += acc.double()
        metrics = {"train_loss": dist.mean(float(total) / cfg.steps_per_epoch),
                   "train_acc": dist.mean(float(total_acc) / cfg.steps_per_epoch)}
        metrics.update(validate(model))
        metrics = dist.broadcast(metrics)   # rank 0's values drive the schedule on every rank
        value = metrics[objective.name]
        final = stages is None or stages.final   # the stage this epoch trained in
        if stages is not None:
            metrics.update(stages.end_epoch(cfg.steps_per_epoch, metrics))
        first = store.segment_unit if init is not None and init.restart_lr else 0
        if final and (unit - first) * cfg.steps_per_epoch >= cfg.warmup_steps:
            sched.step(value)
        return Unit(value, {**metrics, "lr": opt.param_groups[0]["lr"]}, patience=1 if final else 0)

    def keep_best(unit: int, value: float) -> None:
        if dist.is_main():
            save_checkpoint(out / BEST, model, domain, token_names, {"unit": unit, "val": value})

    def restore_best() -> None:
        if not (out / BEST).exists():   # a segment of no epochs: its model is the one it continued
            keep_best(store.segment_unit, math.nan)
            return
        model.load_state_dict(read_checkpoint(out / BEST)["state_dict"])

    store = _LastCheckpoint(out / LAST, model, opt, sched, domain, token_names, setup.fingerprint, stages, init,
                            setup.extra)
    loop = Loop("epoch", objective, Limits(cfg.max_epochs, cfg.patience, cfg.min_delta, setup.budget_seconds),
                store)
    return loop.run(epoch, keep_best=keep_best, restore_best=restore_best, on_unit=setup.on_unit,
                    progress=setup.desc)
