"""The IoU metric and its fast bit counting."""
from __future__ import annotations

import math

import pytest
import torch

from plad.metrics import IOU, count_true, iou


@pytest.mark.parametrize("shape", [(7, 3), (5, 64, 64), (4, 32, 32, 32), (2, 64, 64, 64), (0, 5)])
def test_count_true_equals_sum(shape):
    g = torch.Generator().manual_seed(0)
    flags = torch.rand(*shape, generator=g) < 0.4
    assert torch.equal(count_true(flags), flags.reshape(shape[0], math.prod(shape[1:])).sum(1))


def test_count_true_full_rows_do_not_overflow_lanes():
    # every byte lane of every word set: the largest sums the folding has to carry
    assert count_true(torch.ones(3, 64, 64, 64, dtype=torch.bool)).tolist() == [64 ** 3] * 3


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
