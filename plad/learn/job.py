"""A fine-tuning job: what every fine-tuning method (PLAD rounds, RL) is given.

The same model, target shapes, output folder, seed and wall-clock budget go
to every method of the comparison, so they travel together; each method adds
its own config (:class:`plad.learn.rounds.RoundsConfig`, :class:`plad.learn.rl.RLConfig`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plad.device import FP32, Precision
from plad.domains.base import Domain
from plad.model.network import PLADNet


@dataclass
class Job:
    model: PLADNet              # p(z|x) to fine-tune, in place; it ends with the selected (best) weights
    domain: Domain
    train: np.ndarray           # (N, *domain.shape) bool: the real training shapes
    val: np.ndarray             # (M, *domain.shape) bool: the validation shapes that select the model
    out_dir: Path               # resumable state and results of this run
    seed: int = 0
    #: wall-clock budget of the whole run in seconds, across resumes (see plad.learn.loop.budget_seconds)
    budget_seconds: float = math.inf
    #: the arithmetic of every training forward pass (:mod:`plad.device`); decoding stays float32
    precision: Precision = field(default=FP32)

    def __post_init__(self) -> None:
        self.out_dir = Path(self.out_dir)
