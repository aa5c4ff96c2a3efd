"""REINFORCE fine-tuning, the paper's baseline (after CSGNet).

Programs are sampled from p(z|x) under the grammar mask, executed and
rewarded by the domain metric; the loss is
``-(reward - baseline) * (sum of token log-probs / length)`` with an
exponential moving average of the batch mean reward as the baseline, and SGD
with momentum. Rewards: a similarity in [0, 1] (IoU) is the reward itself; a
distance (the 2D Chamfer distance) becomes CSGNet's
``clip(1 - d / diagonal, 0, 1) ** 20`` with the canvas diagonal (64 * sqrt 2).

Under torchrun (:mod:`plad.learn.distributed`) each rank samples programs for its
own batches of shapes, the baseline follows the mean reward over all ranks
and the gradients are averaged (DDP), so the ranks keep equal weights,
optimizer and baseline; rank 0 writes the files.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from plad.device import FP32, Precision, to_device
from plad.domains.base import Domain
from plad.layout import BEST, STATE
from plad.learn import distributed as dist
from plad.learn.job import Job
from plad.learn.loop import JsonStore, Limits, Loop, Unit
from plad.learn.method_registry import Method
from plad.model.checkpoint import read_checkpoint, save_checkpoint
from plad.model.network import PLADNet
from plad.model.sampling import NEG, ancestral_sample


@dataclass
class RLConfig:
    lr: float = 1e-3
    momentum: float = 0.9
    batch_size: int = 100
    #: batches whose gradients are accumulated into one optimizer step (3D: 10)
    accumulate: int = 1
    #: gradient-norm clip (3D: 10); None for none
    grad_clip: float | None = None
    #: weight of the old value in the moving-average baseline
    baseline_alpha: float = 0.7
    #: batches between validations ("epochs" of RL training)
    steps_per_epoch: int = 100
    max_epochs: int = 100_000
    #: beam of the validation that selects the model (as PLAD's round validation)
    val_beam: int = 5
    val_batch: int = 100
    #: epochs without a validation improvement of at least ``min_delta`` before stopping
    patience: int = 1000
    min_delta: float = 0.005


def reward(domain: Domain, values: torch.Tensor) -> torch.Tensor:
    """Metric values (N,) -> rewards in [0, 1], as the domain declares them (:meth:`Domain.reward`)."""
    return domain.reward(values)


def sample_programs(model: PLADNet, domain: Domain, shapes: torch.Tensor,
                    generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Ancestral sampling of p(z|x) under the grammar mask -> (tokens (N, L) long, lengths (N,))."""
    with torch.no_grad():
        return ancestral_sample(model, domain.tokens, model.encode(shapes), generator)


def masked_log_probs(model: PLADNet, domain: Domain, shapes: torch.Tensor, tokens: torch.Tensor,
                     lengths: torch.Tensor) -> torch.Tensor:
    """Sum of token log-probabilities under the masked (renormalized) policy, with gradient: (N,)."""
    table = domain.tokens
    n, L = tokens.shape
    tokens_in = torch.cat([torch.full((n, 1), model.cfg.bos, dtype=torch.long, device=tokens.device),
                           tokens[:, :-1]], 1)
    logits = model(shapes, tokens_in)                                          # (N, L, V)
    masks = []
    state = table.initial_state(n, tokens.device)
    for pos in range(L):
        masks.append(table.mask(state))
        state = table.advance(state, tokens[:, pos])
    mask = torch.stack(masks, 1)                                                # (N, L, V)
    valid = torch.arange(L, device=tokens.device)[None, :] < lengths[:, None]
    mask = mask | ~valid[:, :, None]  # past the end: any value, ignored below
    logp = torch.log_softmax(logits.float().masked_fill(~mask, NEG), -1)
    picked = logp.gather(2, tokens[:, :, None])[:, :, 0]
    return (picked * valid).sum(1)


class Reinforce:
    """One REINFORCE learner: call :meth:`step` with batches of real training shapes."""

    def __init__(self, model: PLADNet, domain: Domain, cfg: RLConfig, seed: int = 0, precision: Precision = FP32):
        self.model, self.domain, self.cfg, self.precision = model, domain, cfg, precision
        self.opt = torch.optim.SGD(model.parameters(), lr=cfg.lr, momentum=cfg.momentum)
        self.baseline: float | None = None
        self.batches = 0
        self.generator = torch.Generator(device=next(model.parameters()).device).manual_seed(seed)
        self.log_probs = dist.data_parallel(model, lambda m, *a: masked_log_probs(m, domain, *a))

    def step(self, shapes: torch.Tensor) -> dict[str, float]:
        model, domain = self.model, self.domain
        model.eval()  # sample without dropout, as the policy that is evaluated
        tokens, lengths = sample_programs(model, domain, shapes, self.generator)
        with torch.no_grad():
            values = domain.metric(domain.execute(tokens), shapes)
            r = reward(domain, values).float()
        mean_r = dist.mean(float(r.mean()))   # one baseline for every rank
        self.baseline = mean_r if self.baseline is None else (
            self.cfg.baseline_alpha * self.baseline + (1 - self.cfg.baseline_alpha) * mean_r)
        model.train()
        with self.precision.autocast():   # sampling above stays float32, as every decoding
            logp = self.log_probs(shapes, tokens, lengths)
        loss = -((r - self.baseline) * logp / lengths.float()).mean() / self.cfg.accumulate
        loss.backward()
        self.batches += 1
        if self.batches % self.cfg.accumulate == 0:
            if self.cfg.grad_clip:
                torch.nn.utils.clip_grad_norm_(model.parameters(), self.cfg.grad_clip)
            self.opt.step()
            self.opt.zero_grad(set_to_none=True)
        return {"reward": mean_r, "baseline": self.baseline, "loss": float(loss.detach()),
                f"train_{domain.metric.name}": float(values.mean())}


def run_rl(job: Job, cfg: RLConfig, on_unit: Callable[[int, dict[str, Any]], None] | None = None) -> dict:
    """REINFORCE fine-tuning on the real training shapes, with the same budget and selection as PLAD.

    Every ``steps_per_epoch`` batches the model is validated (beam ``val_beam``);
    the best one is kept in ``best.pt``. Stops on ``patience``, ``max_epochs``
    or the wall-clock budget. The learner (weights, optimizer, baseline,
    sampling generator) is saved atomically after every epoch, so a killed run
    resumes where it was; ``state.json`` holds the history like PLAD's rounds.
    """
    from plad.learn.rounds import mean_metric

    model, domain, out, seed = job.model, job.domain, job.out_dir, job.seed
    out.mkdir(parents=True, exist_ok=True)
    names = domain.tokens.names
    device = next(model.parameters()).device
    learner = Reinforce(model, domain, cfg, seed=seed, precision=job.precision)
    learner_file = out / "learner.pt"

    def validate() -> float:
        return mean_metric(model, domain, job.val, cfg.val_beam, cfg.val_batch)

    def save(unit: int, folder: Path) -> None:   # staged, then moved to out/ by the store's commit
        save_checkpoint(folder / learner_file.name, model, domain.name, names, {
            "optimizer": learner.opt.state_dict(), "generator": learner.generator.get_state(),
            "baseline": learner.baseline, "batches": learner.batches})

    def restore() -> None:
        payload = read_checkpoint(learner_file)
        model.load_state_dict(payload["state_dict"])
        learner.opt.load_state_dict(payload["optimizer"])
        learner.generator.set_state(payload["generator"])
        learner.baseline, learner.batches = payload["baseline"], payload["batches"]

    def keep_best(unit: int, value: float) -> None:
        if dist.is_main():
            save_checkpoint(out / BEST, model, domain.name, names, {"unit": unit, "val": value})

    def restore_best() -> None:
        model.load_state_dict(read_checkpoint(out / BEST)["state_dict"])

    def epoch(unit: int, remaining: Callable[[], float]) -> Unit:
        rng = np.random.default_rng([dist.rank_seed(seed), unit])   # this rank's batches
        torch.manual_seed(dist.rank_seed(seed * 1_000_003 + unit))   # dropout masks: a resumed epoch draws the same
        if dist.world() > 1:   # only rank 0's sampling state is saved: the others restart theirs every epoch
            learner.generator.manual_seed(dist.rank_seed(seed * 1_000_003 + unit + 2**62))
        totals: dict[str, float] = {}
        for _ in range(cfg.steps_per_epoch):
            idx = np.sort(rng.choice(len(job.train), size=cfg.batch_size, replace=cfg.batch_size > len(job.train)))
            step = learner.step(to_device(job.train[idx], device))
            for k, v in step.items():
                totals[k] = totals.get(k, 0.0) + v / cfg.steps_per_epoch
        model.eval()
        return Unit(validate(), totals)

    loop = Loop("epoch", domain.metric, Limits(cfg.max_epochs, cfg.patience, cfg.min_delta, job.budget_seconds),
                JsonStore(out / STATE, save=save, restore=restore))
    result = loop.run(epoch, start=validate, keep_best=keep_best, restore_best=restore_best, on_unit=on_unit)
    return {"method": "rl", **result.summary()}


class _RL(Method):
    """The ``rl`` method: :func:`run_rl` with ``finetune.<domain>.rl``; its work is ``rl.max_epochs``."""

    checkpoint = "learner.pt"

    def check(self, spec, cfg, where: str) -> None:
        if spec.max_rounds is not None:
            raise ValueError(f"{where}.max_rounds: RL has no rounds; its epochs are rl.max_epochs")
        if spec.search is not None:
            raise ValueError(f"{where}.search: RL has no P_BEST to search for")

    def work(self, spec, cfg) -> dict[str, int]:
        return {"max_epochs": cfg.rl.max_epochs}

    def run(self, job: Job, spec, cfg, hooks) -> dict:
        return run_rl(job, cfg.rl, on_unit=hooks.on_unit)


#: the registered ``rl`` method (:mod:`plad.learn.method_registry`)
RL = _RL()
