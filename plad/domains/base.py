"""The domain plugin protocol.

A domain is everything that is specific to one shape language: its token
table (grammar), the text form of programs, a batched executor, a synthetic
program sampler, its target (real) data and its metric. Model, search,
training methods and metrics code stay generic and only talk to this.
"""
from __future__ import annotations

import abc
import os
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from plad.grammar import ProgramError, TokenTable
from plad.metrics import Metric

if TYPE_CHECKING:  # pragma: no cover
    from plad.rewrite.space import RewriteSpace


class Domain(abc.ABC):
    """Base class of domain plugins. Subclasses set the class attributes and implement the methods."""

    #: registry name, e.g. ``"csg2d"``
    name: str
    #: shape of one executed program / target, e.g. ``(64, 64)`` or ``(32, 32, 32)``
    shape: tuple[int, ...]
    #: the domain's reconstruction metric (declares whether higher is better)
    metric: Metric
    #: optional: program rewriting and search support (the moves, program structure and
    #: candidate generators of :mod:`plad.rewrite`); None: the domain has no search support
    rewrite: "RewriteSpace | None" = None

    @property
    @abc.abstractmethod
    def tokens(self) -> TokenTable:
        """The token table; it alone defines validity, decoding masks and the length cap."""

    # -- text form ---------------------------------------------------------------
    @abc.abstractmethod
    def parse(self, text: str) -> list[int]:
        """Program text -> token ids. Raises :class:`ProgramError` naming the bad token."""

    @abc.abstractmethod
    def format(self, ids: Sequence[int]) -> str:
        """Token ids -> program text (the inverse of :meth:`parse` for valid programs)."""

    def check(self, ids: Sequence[int]) -> None:
        """Raise :class:`ProgramError` if ``ids`` is not a complete valid program."""
        self.tokens.check(ids)

    # -- execution -----------------------------------------------------------------
    @abc.abstractmethod
    def execute(self, programs: torch.Tensor) -> torch.Tensor:
        """Execute a batch of valid programs.

        ``programs``: (B, L) long token ids, each row a complete valid program
        followed by any padding (ignored). Returns (B, *shape) bool on the
        same device.
        """

    # -- synthetic data ----------------------------------------------------------------
    @abc.abstractmethod
    def sample(self, n: int, generator: np.random.Generator) -> list[list[int]]:
        """``n`` valid, non-degenerate synthetic programs for supervised pretraining."""

    # -- real data -----------------------------------------------------------------
    @abc.abstractmethod
    def target_data(self, split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
        """Real target shapes of a split (``train``/``val``/``test``): bool (N, *shape)."""

    # -- outputs of inferred programs ------------------------------------------------------------
    def export_files(self, ids: Sequence[int], stem: Path) -> list[Path]:
        """Write files that carry the valid program ``ids`` into other tools, named ``stem`` plus a
        suffix (e.g. ``.svg``, ``.ply``, ``.scad``); return their paths. Default: none."""
        return []


def pad_programs(programs: Sequence[Sequence[int]], pad: int = 0,
                 device: str | torch.device = "cpu") -> torch.Tensor:
    """(B, L) long tensor of right-padded token ids (padding is ignored by executors)."""
    L = max((len(p) for p in programs), default=1)
    out = torch.full((len(programs), max(L, 1)), pad, dtype=torch.long)
    for i, p in enumerate(programs):
        if len(p):
            out[i, : len(p)] = torch.as_tensor(list(p), dtype=torch.long)
    return out.to(device)


def split_padding(programs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """-1-padded token rows (N, L) -> (rows with padding replaced by 0, lengths (N,)).

    Programs are stored -1-padded on disk; executors and the model take
    0-padded rows plus lengths.
    """
    return programs.clamp(min=0), (programs >= 0).sum(1)


__all__ = ["Domain", "ProgramError", "pad_programs", "split_padding"]
