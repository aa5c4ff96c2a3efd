"""Building blocks of plad.rewrite: bit counting, packed IoU, residual boxes, candidate batches."""
from __future__ import annotations

import numpy as np
import torch

from plad.domains import bits
from plad.domains.bits import packed_iou, popcount, row_popcount
from plad.domains.boxes import grow_box, prefix_sums, residual_boxes
from plad.domains.csg2d.executor import pack as pack2d
from plad.domains.csg3d.executor import pack as pack3d
from plad.domains.space import Candidates
from plad.metrics import iou
from plad.rewrite.evaluate import first_per_group, top_per_group


def test_popcount_of_int64_words():
    g = torch.Generator().manual_seed(0)
    words = torch.randint(-2 ** 63, 2 ** 63 - 1, (2000,), generator=g, dtype=torch.int64)
    expected = [bin(w & (2 ** 64 - 1)).count("1") for w in words.tolist()]
    assert popcount(words).tolist() == expected
    assert popcount(torch.tensor([-1, 0, 1, -2 ** 63])).tolist() == [64, 0, 1, 1]


def test_numpys_popcount_and_the_tensor_arithmetic_give_the_same_counts(monkeypatch):
    """The CPU path (numpy's bitwise_count on the words viewed unsigned) and the SWAR path (any device) agree
    word by word and row by row, on negative words and on strided views."""
    g = torch.Generator().manual_seed(3)
    words = torch.randint(-2 ** 63, 2 ** 63 - 1, (300, 64), generator=g, dtype=torch.int64)
    words[0, :4] = torch.tensor([-1, -2 ** 63, 0, 2 ** 63 - 1])
    strided = words[::3, 1::2]
    fast = [popcount(words), row_popcount(words), popcount(strided), row_popcount(strided)]
    assert fast[1][0].item() == 64 + 1 + 0 + 63 + int(popcount(words[0, 4:]).sum())
    monkeypatch.setattr(bits, "_BITWISE_COUNT", None)
    slow = [popcount(words), row_popcount(words), popcount(strided), row_popcount(strided)]
    for a, b in zip(fast, slow):
        assert a.dtype == b.dtype == torch.int64 and torch.equal(a, b)
    assert torch.equal(slow[1], slow[0].sum(1))


def test_packed_iou_is_the_iou_metric():
    g = torch.Generator().manual_seed(1)
    for shape, pack in (((64, 64), pack2d), ((32, 32, 32), pack3d)):
        a = torch.rand(40, *shape, generator=g) < 0.3
        b = torch.rand(40, *shape, generator=g) < 0.2
        b[0] = a[0]
        a[1], b[1] = False, False                       # two empty shapes: IoU 1, like the metric
        assert torch.equal(packed_iou(pack(a), pack(b)), iou(a, b))


def test_residual_boxes_bound_and_grow_inside_components():
    mask = np.zeros((32, 32, 32), dtype=bool)
    mask[2:6, 3:9, 1:5] = True                          # a box of 96 voxels
    mask[4:6, 3:5, 5:12] = True                         # a bar sticking out of it: one component of 124
    mask[20:23, 20:23, 20:23] = True                    # a separate cube of 27
    boxes = residual_boxes(mask, components=2)
    assert boxes[0] == ([2, 3, 1], [5, 8, 11])          # bounding box of the larger component
    assert boxes[1] == ([2, 3, 1], [5, 8, 4])           # the box grown inside it from its deepest voxel
    assert boxes[2] == boxes[3] == ([20, 20, 20], [22, 22, 22])
    assert residual_boxes(mask, components=1, bounding=False) == [boxes[1]]
    assert residual_boxes(np.zeros_like(mask), components=2) == []
    # more grown boxes: the next seed is the deepest voxel the first box leaves uncovered (the bar),
    # and the box grows from it through the whole mask; a component that is covered stops early
    assert residual_boxes(mask, components=2, bounding=False, grown=3) == [
        boxes[1], ([4, 3, 1], [5, 4, 11]), boxes[3]]
    assert grow_box(prefix_sums(mask), (21, 21, 21)) == ([20, 20, 20], [22, 22, 22])


def test_residual_boxes_equal_the_frozen_reference_box_for_box():
    """The int32 summed-volume table and the face-by-face growing give the boxes of the code before them
    (tests/reference/boxes_v0.py) on random masks: unions of boxes, with holes, noise, touching the border."""
    from tests.reference import boxes_v0

    rng = np.random.default_rng(1)
    for i in range(120):
        mask = np.zeros((32, 32, 32), dtype=bool)
        for _ in range(rng.integers(1, 6)):
            lo = rng.integers(-4, 30, 3).clip(0)
            hi = lo + rng.integers(1, 20, 3)
            mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
        if i % 3:
            mask &= rng.random(mask.shape) < 0.95
        if i % 7 == 0:
            mask = rng.random(mask.shape) < 0.5
        assert np.array_equal(prefix_sums(mask), boxes_v0.prefix_sums(mask))
        for components, bounding, grown in ((3, True, 1), (2, False, 3)):
            want = boxes_v0.residual_boxes(mask, components, bounding, grown)
            got = residual_boxes(mask, components, bounding, grown)
            assert [([int(v) for v in lo], [int(v) for v in hi]) for lo, hi in got] == \
                [([int(v) for v in lo], [int(v) for v in hi]) for lo, hi in want]


def test_group_selection_prefers_value_then_fewer_tokens():
    owner = np.array([0, 0, 0, 2, 2])
    values = np.array([1.0, 0.5, 0.5, 3.0, 2.0])        # lower is better here
    lengths = np.array([5, 7, 6, 4, 4])
    assert first_per_group(owner, values, lengths).tolist() == [2, -1, 4]
    # screen: higher is better; ties go to fewer tokens, then the first row
    score = np.array([0.9, 0.9, 0.1, 0.5, 0.5])
    assert top_per_group(score, np.array([6, 5, 5, 4, 4]), owner, keep=1).tolist() == [1, 3]


def test_candidates_concat_keeps_templates():
    a = Candidates(torch.tensor([[1, 2, 3], [1, 4, 3]]), torch.tensor([3, 3]), torch.tensor([0, 0]),
                   bases=torch.tensor([[1, 2, 3]]), base=torch.tensor([0, 0]), position=torch.tensor([1, 1]))
    b = Candidates(torch.tensor([[5, 6]]), torch.tensor([2]), torch.tensor([1]),
                   bases=torch.tensor([[5, 0]]), base=torch.tensor([0]), position=torch.tensor([1]))
    c = Candidates.concat([a, b])
    assert c.tokens.tolist() == [[1, 2, 3], [1, 4, 3], [5, 6, 0]]
    assert c.base.tolist() == [0, 0, 1] and c.bases.tolist() == [[1, 2, 3], [5, 0, 0]]
    for i in range(len(c)):
        row = c.bases[c.base[i]].clone()
        row[c.position[i]] = c.tokens[i, c.position[i]]
        assert row[: int(c.lengths[i])].tolist() == c.row(i)
    assert Candidates.concat([a, Candidates.from_lists([[7]], [2])]).bases is None
