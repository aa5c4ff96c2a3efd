"""Pretraining curriculum by program complexity, with replay of easy programs.

Why: with many primitives per program the first tokens barely depend on the
shape, so a network trained on the full mix from the start learns to ignore
its input (issue 14: a prefix-swap loss gap of 0.009 nats/token after 150
steps on 2-12 primitives, 0.30 on 1-primitive programs). A curriculum starts
on the simplest programs, where the shape decides the tokens, and widens the
mix stage by stage; a curriculum without replay forgets the easy programs
within a few dozen steps, so a share of every batch keeps coming from them.

Stages: ``stages`` lists the maximum complexity of each stage
(:meth:`plad.domains.base.Domain.complexity`: primitives of CSG, cuboids of
ShapeAssembly); after them comes the final stage, which takes every
program. A stage whose maximum is below the smallest complexity in the data
trains on the smallest complexity present. A stage ends, at an epoch's end,
when the first of these holds: it has trained ``stage_steps`` steps; the
prefix-swap gap (:mod:`plad.learn.diagnostics`) on validation programs of the
stage reached ``advance_gap``; the
token accuracy on the validation programs of the stage reached
``advance_acc``; its validation loss has not improved for
``stage_patience`` epochs (early stop per stage). The final stage ends with
the training loop itself. Until the final stage the loop's patience does
not run and the learning rate is not reduced (see :func:`plad.learn.train.fit`).

Batches: every step draws ``batch_size x world`` program indices from a
stream fixed by (seed, epoch), the same on every rank: ``round(replay x
batch)`` of them uniformly from the easy programs (complexity at most
``stages[0]``, or the smallest present), the rest uniformly from the stage's
programs; rank r takes the r-th ``batch_size`` of them. So a distributed
run (:mod:`plad.learn.distributed`) needs no per-rank state, and a resumed run
draws the same batches: the stage is part of the checkpointed state
(:meth:`Curriculum.state_dict`).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from plad.learn import distributed as dist


@dataclass
class CurriculumConfig:
    """``pretrain.<domain>.curriculum``. Off by default (the paper's plain schedule)."""

    enabled: bool = False
    #: maximum complexity of each stage before the final one, which takes every program
    stages: list[int] = field(default_factory=list)
    #: a stage ends after this many training steps (rounded up to whole epochs); None: no step limit
    stage_steps: int | None = None
    #: a stage ends once the prefix-swap gap (nats/token) on its validation programs reaches this; None: not used
    advance_gap: float | None = None
    #: a stage ends once the token accuracy on its validation programs reaches this; None: not used
    advance_acc: float | None = None
    #: a stage ends after this many epochs without improving its validation loss; None: not used
    stage_patience: int | None = None
    #: share of every batch drawn from the easy programs (the first stage's), in [0, 1)
    replay: float = 0.0

    def __post_init__(self) -> None:
        self.stages = [int(s) for s in self.stages]
        if not 0.0 <= self.replay < 1.0:
            raise ValueError(f"curriculum.replay {self.replay} must be in [0, 1)")
        if self.stages != sorted(self.stages):
            raise ValueError(f"curriculum.stages {self.stages} must be increasing")
        if self.enabled and not self.stages:
            raise ValueError("curriculum.enabled needs at least one entry in curriculum.stages")
        if self.enabled and self.stage_steps is None and self.advance_gap is None and \
                self.advance_acc is None and self.stage_patience is None:
            raise ValueError("curriculum: no rule ends a stage (stage_steps, advance_gap, advance_acc, stage_patience)")


def pool(complexity: np.ndarray, max_complexity: int | None) -> np.ndarray:
    """Indices of the programs of complexity at most ``max_complexity`` (None: all); if there are none, those
    of the smallest complexity present."""
    if max_complexity is None:
        return np.arange(len(complexity))
    limit = max(int(max_complexity), int(complexity.min()))
    return np.flatnonzero(complexity <= limit)


class Curriculum:
    """The stage, its bookkeeping and its batches (see the module docstring)."""

    def __init__(self, cfg: CurriculumConfig, complexity: np.ndarray, val_complexity: np.ndarray):
        if len(complexity) == 0:
            raise ValueError("curriculum: no training programs")
        self.cfg = cfg
        self.complexity, self.val_complexity = np.asarray(complexity), np.asarray(val_complexity)
        self.stage = 0
        self.stage_steps = 0                # steps trained in the current stage
        self.best_loss = float("inf")       # the stage's best validation loss, for stage_patience
        self.stale = 0                      # epochs since it improved
        self.easy = pool(self.complexity, cfg.stages[0] if cfg.stages else None)

    # -- the stage ------------------------------------------------------------------------------
    @property
    def num_stages(self) -> int:
        return len(self.cfg.stages) + 1

    @property
    def final(self) -> bool:
        """In the last stage (every program): the loop's patience and the schedule apply."""
        return self.stage >= self.num_stages - 1

    @property
    def max_complexity(self) -> int | None:
        """The current stage's maximum complexity (None: the final stage, every program)."""
        return None if self.final else self.cfg.stages[self.stage]

    def val_mask(self) -> np.ndarray:
        """Which validation programs belong to the current stage."""
        return np.isin(np.arange(len(self.val_complexity)), pool(self.val_complexity, self.max_complexity))

    def end_epoch(self, steps: int, metrics: dict[str, float]) -> dict[str, float]:
        """After an epoch of ``steps`` steps with validation ``metrics`` (``stage_prefix_gap``, else
        ``prefix_gap``; ``stage_val_loss``, ``stage_val_acc``): advance if a rule says so. Returns the history
        columns of the epoch."""
        row = {"curriculum_stage": float(self.stage)}
        if self.final:
            return row
        cfg = self.cfg
        self.stage_steps += steps
        loss = metrics.get("stage_val_loss", float("inf"))
        if loss < self.best_loss - 1e-3:
            self.best_loss, self.stale = loss, 0
        else:
            self.stale += 1
        gap = metrics.get("stage_prefix_gap", metrics.get("prefix_gap", -np.inf))
        advance = (cfg.stage_steps is not None and self.stage_steps >= cfg.stage_steps) \
            or (cfg.advance_gap is not None and gap >= cfg.advance_gap) \
            or (cfg.advance_acc is not None and metrics.get("stage_val_acc", -np.inf) >= cfg.advance_acc) \
            or (cfg.stage_patience is not None and self.stale >= cfg.stage_patience)
        if advance:
            self.stage += 1
            self.stage_steps, self.best_loss, self.stale = 0, float("inf"), 0
        return row

    def state_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "stage_steps": self.stage_steps, "best_loss": self.best_loss,
                "stale": self.stale, "config": asdict(self.cfg)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.stage, self.stage_steps = int(state["stage"]), int(state["stage_steps"])
        self.best_loss, self.stale = float(state["best_loss"]), int(state["stale"])

    # -- batches --------------------------------------------------------------------------------
    def indices(self, epoch: int, seed: int, batch_size: int) -> Iterator[np.ndarray]:
        """This rank's program indices of every step of ``epoch`` (the stage is read now): (batch_size,) each."""
        rng = np.random.default_rng([seed, epoch, self.stage])   # the same stream on every rank
        stage = pool(self.complexity, self.max_complexity)
        world, rank = dist.world(), dist.rank()
        total = batch_size * world
        n_easy = int(round(self.cfg.replay * total))
        while True:
            picks = np.concatenate([self.easy[rng.integers(0, len(self.easy), n_easy)],
                                    stage[rng.integers(0, len(stage), total - n_easy)]])
            picks = picks[rng.permutation(total)]   # easy rows spread over the ranks
            yield picks[rank * batch_size:(rank + 1) * batch_size]

    def batches(self, epoch: int, seed: int, batch_size: int, programs: torch.Tensor) -> Iterator[torch.Tensor]:
        """The -1-padded program rows of this rank's batches of ``epoch``."""
        for idx in self.indices(epoch, seed, batch_size):
            yield programs[torch.from_numpy(idx)]


__all__ = ["Curriculum", "CurriculumConfig", "pool"]
