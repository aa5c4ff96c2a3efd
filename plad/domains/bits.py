"""Bit counting on bit-packed shapes, for cheap screening scores.

Executors that pack a shape into integer words (one bit per pixel or voxel)
can be screened without unpacking: IoU of two packed shapes is two popcounts.
torch has no popcount, so :func:`popcount` is the classic SWAR bit count on
int64 words (two's-complement wrap-around is what the trick needs; the masks
clear the bits that arithmetic right shifts fill in).
"""
from __future__ import annotations

import torch

_M1, _M2, _M4, _H01 = 0x5555555555555555, 0x3333333333333333, 0x0F0F0F0F0F0F0F0F, 0x0101010101010101


def popcount(words: torch.Tensor) -> torch.Tensor:
    """Set bits of each int64 word (any shape) -> int64, same shape."""
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
    inter = popcount(a & b).sum(1)
    union = popcount(a | b).sum(1)
    return torch.where(union > 0, inter.double() / union.clamp(min=1).double(),
                       torch.ones_like(union, dtype=torch.float64))
