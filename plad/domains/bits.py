"""Bit counting on bit-packed shapes, for cheap screening scores.

Executors that pack a shape into integer words (one bit per pixel or voxel)
can be screened without unpacking: IoU of two packed shapes is two popcounts.
torch has no popcount: on the CPU numpy's ``bitwise_count`` (numpy >= 2; one
hardware popcount per word, about 30x the tensor arithmetic below on 64-word
canvases) counts the words viewed as unsigned (on signed words it counts the
absolute value's bits); elsewhere the classic SWAR bit count on int64 words
(two's-complement wrap-around is what the trick needs; the masks clear the bits
that arithmetic right shifts fill in). Both give the same exact counts.
"""
from __future__ import annotations

import numpy as np
import torch

#: numpy's hardware popcount (numpy >= 2.0)
_BITWISE_COUNT = getattr(np, "bitwise_count", None)

_M1, _M2, _M4, _H01 = 0x5555555555555555, 0x3333333333333333, 0x0F0F0F0F0F0F0F0F, 0x0101010101010101


def _counts(words: torch.Tensor) -> np.ndarray | None:
    """Set bits of each word as a uint8 array (numpy's popcount), or None where it does not apply."""
    if _BITWISE_COUNT is None or words.device.type != "cpu" or words.dtype != torch.int64 or words.requires_grad:
        return None
    return _BITWISE_COUNT(words.numpy().view(np.uint64))


def popcount(words: torch.Tensor) -> torch.Tensor:
    """Set bits of each int64 word (any shape) -> int64, same shape."""
    counts = _counts(words)
    if counts is not None:
        return torch.from_numpy(counts.astype(np.int64))
    return _swar(words)


def row_popcount(words: torch.Tensor) -> torch.Tensor:
    """Set bits of each row: (C, ...) int64 words -> int64 (C,), the sum of :func:`popcount` over a row."""
    words = words.reshape(words.shape[0], -1)
    counts = _counts(words)
    if counts is not None:
        return torch.from_numpy(counts.sum(1, dtype=np.int64))
    return _swar(words).sum(1)


def _swar(words: torch.Tensor) -> torch.Tensor:
    """:func:`popcount` in tensor arithmetic (any device)."""
    x = words - ((words >> 1) & _M1)
    x = (x & _M2) + ((x >> 2) & _M2)
    x = (x + (x >> 4)) & _M4
    return (x * _H01) >> 56          # top byte: sum of the 8 byte counts (<= 64, so non-negative)


def packed_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of packed shapes: a, b (C, ...) of int64 (or int32, reinterpreted in pairs) words -> float64 (C,).

    Two empty shapes have IoU 1, as :func:`plad.metrics.iou`.
    """
    a = a.reshape(a.shape[0], -1)
    b = b.reshape(b.shape[0], -1)
    if a.dtype != torch.int64:
        a, b = a.contiguous().view(torch.int64), b.contiguous().view(torch.int64)
    inter = row_popcount(a & b)
    union = row_popcount(a | b)
    return torch.where(union > 0, inter.double() / union.clamp(min=1).double(),
                       torch.ones_like(union, dtype=torch.float64))
