"""Canonical 2D CSG programs and the one-primitive floor.

Canonical form (docs/domains.md, "Canonical programs"): the operands of ``+``
(union) and ``*`` (intersection) are ordered by their token sequences,
smaller first; ``-`` keeps its order. Draw tokens need no snapping: the 424
tokens of the vocabulary render 424 distinct bitmaps (checked by
``tests/plad/domains/test_canonical.py``), so no two of them are interchangeable.

The one-primitive floor is, per target, the draw token whose canvas has the
best Chamfer distance to it. Every draw token's edges and distance map are
computed once, so the distances of all N x 424 pairs are two matrix
products; the metric's own definition (docs/domains.md, "Metric") is kept,
and the evaluation scores the chosen programs with the metric itself.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from plad.domains.csg2d.tokens import token_table
from plad.metrics.chamfer import PENALTY, canny_binary, distance_maps

_COMMUTATIVE = {"union", "intersection"}


def canonical_program(ids: Sequence[int]) -> list[int]:
    """The canonical form of a valid csg2d program (token ids ending with ``$``)."""
    table = token_table()
    stack: list[list[int]] = []
    for i in ids:
        tok = table.tokens[int(i)]
        if tok.stop:
            break
        if tok.kind == "draw":
            stack.append([int(i)])
            continue
        b, a = stack.pop(), stack.pop()      # postfix: ``a b op``
        if tok.kind in _COMMUTATIVE and b < a:
            a, b = b, a
        stack.append(a + b + [int(i)])
    (program,) = stack
    return program + [table.index("$")]


def _edge_features(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """bool (N, H, W) -> (edges float64 (N, H*W), distances float64 (N, H*W), degenerate (N,) bool)."""
    edges = canny_binary(images)
    dist = distance_maps(edges).double()
    counts = edges.flatten(1).sum(1)
    degenerate = (counts == 0) | (counts == edges[0].numel())
    dist[~edges.flatten(1).any(1)] = 0          # no edge: float32 max, never used (degenerate)
    return edges.flatten(1).double(), dist.flatten(1), degenerate


def one_primitive(targets: np.ndarray, bitmaps: torch.Tensor, draws: np.ndarray, chunk: int = 500) -> list[list[int]]:
    """The one-primitive floor: per target (bool (N, 64, 64)) the program ``<draw> $`` of the draw token with the
    lowest Chamfer distance (the first on ties). ``bitmaps`` (V, 64, 64) bool, ``draws`` the draw token ids."""
    table = token_table()
    stop = table.index("$")
    e_p, d_p, bad_p = _edge_features(bitmaps[torch.from_numpy(draws)])       # (K, HW)
    n_p = e_p.sum(1)                                                          # |E_P| (K,)
    out: list[list[int]] = []
    for start in range(0, len(targets), chunk):
        e_t, d_t, bad_t = _edge_features(torch.from_numpy(targets[start:start + chunk]))
        n_t = e_t.sum(1)
        # CSGNet's CD with E in {0, 255}: sum(D * E) / (sum(E) + 1), averaged over both directions
        over_p = (d_t @ e_p.T) * 255 / (n_p[None] * 255 + 1)                  # D_T over E_P: (n, K)
        over_t = (e_t @ d_p.T) * 255 / (n_t[:, None] * 255 + 1)               # D_P over E_T
        cd = ((over_p + over_t) / 2).masked_fill(bad_p[None] | bad_t[:, None], PENALTY)
        best = cd.argmin(1).numpy()
        out += [[int(draws[k]), stop] for k in best]
    return out


__all__ = ["canonical_program", "one_primitive"]
