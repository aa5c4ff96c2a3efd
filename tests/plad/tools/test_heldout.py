"""plad.tools.heldout: the held-out slice is the training shapes the labels left out, evenly spaced."""
from __future__ import annotations

import numpy as np

from plad.learn.labels import order
from plad.tools.heldout import held_out_index


def test_the_held_out_shapes_are_the_ones_the_labels_left_out_evenly_spaced():
    n, labelled = 1000, 300
    index = held_out_index(n, labelled, 50)
    rest = order(n)[labelled:]
    assert len(index) == 50 and len(set(index.tolist())) == 50
    assert not set(index.tolist()) & set(order(n)[:labelled].tolist())
    assert index.tolist() == rest[np.linspace(0, len(rest) - 1, 50).round().astype(np.int64)].tolist()
    assert held_out_index(n, labelled, 5000).tolist() == rest.tolist()      # fewer left: all of them
    assert held_out_index(n, n, 10).tolist() == []
