"""The IoU metric and its fast bit counting."""
from __future__ import annotations

import math

import pytest
import torch

from plad.metrics import IOU, count_true, iou


# rows of whole chunks read in place (4,096 bytes and 32^3, 64^3: chunks of 128 words; 136 bytes: one of 17;
# 6,120: three of 255) and rows padded (3 bytes; 104: 13 words, no divisor from 16 to 255; 32,792: 4,099 words)
@pytest.mark.parametrize("shape", [(7, 3), (5, 64, 64), (4, 32, 32, 32), (2, 64, 64, 64), (0, 5), (3, 136),
                                   (3, 6120), (3, 104), (2, 32792)])
def test_count_true_equals_sum(shape):
    g = torch.Generator().manual_seed(0)
    flags = torch.rand(*shape, generator=g) < 0.4
    assert torch.equal(count_true(flags), flags.reshape(shape[0], math.prod(shape[1:])).sum(1))


def test_count_true_full_rows_do_not_overflow_lanes():
    # every byte lane of every word set: the largest sums the folding has to carry
    assert count_true(torch.ones(3, 64, 64, 64, dtype=torch.bool)).tolist() == [64 ** 3] * 3
    for row in (6120, 136, 104):   # chunks of 255 words (the most a byte lane holds), 17, padded
        assert count_true(torch.ones(2, row, dtype=torch.bool)).tolist() == [row] * 2


def test_count_true_reads_a_row_of_whole_chunks_in_place():
    from plad.metrics import _chunk_words

    assert [_chunk_words(b) for b in (32 ** 3, 64 * 64, 6120, 136, 104, 21, 0)] == [128, 128, 255, 17, None, None,
                                                                                     None]
    # a non-contiguous bool view is counted as its values
    flags = torch.rand(6, 4096, generator=torch.Generator().manual_seed(2)) < 0.5
    assert torch.equal(count_true(flags[::2]), flags[::2].sum(1))


def test_iou_matches_its_definition():
    g = torch.Generator().manual_seed(1)
    pred = torch.rand(50, 32, 32, 32, generator=g) < 0.2
    target = torch.rand(50, 32, 32, 32, generator=g) < 0.1
    p, t = pred.reshape(50, -1), target.reshape(50, -1)
    expected = (p & t).sum(1).double() / (p | t).sum(1).double()
    assert torch.equal(iou(pred, target), expected)
    empty = torch.zeros(2, 4, 4, dtype=torch.bool)
    assert iou(empty, empty).tolist() == [1.0, 1.0]
    assert iou(empty, ~empty).tolist() == [0.0, 0.0]
    assert IOU.higher_is_better and IOU.worst == 0.0
