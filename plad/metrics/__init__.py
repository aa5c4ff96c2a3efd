"""Reconstruction metrics. Each declares whether higher is better, so that no
caller needs its own comparator: use :meth:`Metric.better` and :meth:`Metric.best`.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import torch

from plad.metrics.chamfer import PENALTY, TargetFeatures, chamfer, chamfer_against


@dataclass(frozen=True)
class Metric:
    """A per-shape similarity/distance between executed programs and targets.

    ``fn(pred, target)`` takes bool tensors (N, *shape) and returns float64 (N,).
    ``worst`` is the value given to a program that cannot be executed.
    """

    name: str
    higher_is_better: bool
    fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    worst: float
    #: optional: precompute per-target work once (``prepare(target)``) and score
    #: candidates against it (``against(candidates (N, K, *shape), prepared) -> (N, K)``)
    prepare: Callable[[torch.Tensor], Any] | None = None
    against: Callable[[torch.Tensor, Any], torch.Tensor] | None = None

    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return self.fn(pred, target)

    def score_candidates(self, candidates: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Score K candidates per target: candidates (N, K, *shape), target (N, *shape) -> (N, K)."""
        if self.prepare is not None and self.against is not None:
            return self.against(candidates, self.prepare(target))
        n, k = candidates.shape[:2]
        expanded = target.unsqueeze(1).expand_as(candidates)
        return self.fn(candidates.reshape(n * k, *candidates.shape[2:]),
                       expanded.reshape(n * k, *target.shape[1:])).reshape(n, k)

    def better(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Elementwise: ``a`` strictly better than ``b``."""
        return a > b if self.higher_is_better else a < b

    def best_value(self, values: Iterable[float]) -> float | None:
        """The best of plain numbers by this metric's direction (NaNs skipped); ``None`` for none."""
        finite = [float(v) for v in values if not math.isnan(float(v))]
        if not finite:
            return None
        return max(finite) if self.higher_is_better else min(finite)

    def best(self, values: torch.Tensor, dim: int = -1) -> tuple[torch.Tensor, torch.Tensor]:
        """(best values, their indices) along ``dim``; the first index wins ties."""
        return values.max(dim=dim) if self.higher_is_better else values.min(dim=dim)


_LANES8 = 0x00FF00FF00FF00FF
_LANES16 = 0x0000FFFF0000FFFF
_CHUNK_WORDS = 255  # int64 words summed before a byte lane could carry into the next


@functools.lru_cache(maxsize=64)
def _chunk_words(row_bytes: int) -> int | None:
    """The largest number of int64 words, at most :data:`_CHUNK_WORDS` and at least 16, that divides a row of
    ``row_bytes`` bytes into whole chunks (no padding copy), or None."""
    if row_bytes % 8:
        return None
    words = row_bytes // 8
    return next((c for c in range(min(words, _CHUNK_WORDS), 15, -1) if words % c == 0), None)


def count_true(flags: torch.Tensor) -> torch.Tensor:
    """Number of True entries per row of a bool (N, M) tensor -> int64 (N,).

    Same as ``flags.sum(1)``, about 20 times faster on the CPU: torch sums bool
    and uint8 tensors element by element (~0.2 ns/byte here), but int64 ones at
    memory speed. A bool is one byte holding 0 or 1, so each int64 word of the
    row holds 8 byte lanes; summing at most 255 words cannot carry across
    lanes, and the lanes are then folded into 16- and 32-bit lanes (SWAR). Where the words of a row split into
    equal chunks of at most 255, the row is read where it lies; else it is padded with zero bytes (a copy).
    """
    n = flags.shape[0]
    words = flags.reshape(n, math.prod(flags.shape[1:]))
    chunk = _chunk_words(words.shape[1])
    if chunk is None:   # not a whole number of words, or no divisor up to the cap: pad with zeros (a copy)
        chunk = _CHUNK_WORDS
        words = torch.nn.functional.pad(words, (0, (-words.shape[1]) % (8 * chunk)))
    # (n, chunks, chunk) int64 words: a 32^3 grid is 4,096 words, 32 chunks of 128, read in place
    w = words.contiguous().view(torch.int64).view(n, words.shape[1] // (8 * chunk), chunk)
    s = w.sum(2)                                           # (n, chunks): byte lanes <= 255
    s = (s & _LANES8) + ((s >> 8) & _LANES8)               # 16-bit lanes <= 510
    s = (s & _LANES16) + ((s >> 16) & _LANES16)            # 32-bit lanes <= 1020
    s = s.sum(1)                                           # 32-bit lanes <= 1020 * chunks
    return (s & 0xFFFFFFFF) + (s >> 32)


def iou(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Volumetric/areal IoU of bool tensors (N, *shape) -> float64 (N,).

    Two empty shapes are identical: IoU 1.
    """
    p = pred.reshape(pred.shape[0], -1).to(torch.bool)
    t = target.reshape(target.shape[0], -1).to(torch.bool)
    inter = count_true(p & t).double()
    union = count_true(p | t).double()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(union))


IOU = Metric("iou", higher_is_better=True, fn=iou, worst=0.0)


def chamfer_metric() -> Metric:
    """CSGNet's Chamfer distance on 64x64 canvases (lower is better)."""
    return Metric("chamfer", higher_is_better=False, fn=chamfer, worst=PENALTY,
                  prepare=TargetFeatures.of, against=chamfer_against)


__all__ = ["IOU", "Metric", "chamfer_metric", "count_true", "iou"]
