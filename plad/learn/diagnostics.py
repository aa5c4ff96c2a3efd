"""Does the network use its input? The prefix-swap loss gap.

The gap is the mean token cross-entropy of a batch of (shape, program)
pairs when every program is decoded after *another* shape's visual prefix,
minus the loss with its own prefix, in nats per token. A network that
ignores its input has a gap of 0 (its prediction does not depend on the
prefix); one that reads the shape pays for the wrong one. The other shape of
row i is row i+1 (cyclically), so the value is deterministic for a fixed
batch. Reported per pretraining epoch next to the greedy metric on real
validation shapes (issue 14: a 3D model with validation loss going down and
a gap of 0.009 had learnt the programs' statistics, not the shapes). The gap split by the kind of the target
token is a maintainer's probe, :mod:`plad.tools.kind_gaps`.
"""
from __future__ import annotations

import torch

from plad.model.network import PLADNet


@torch.no_grad()
def prefix_gap(model: PLADNet, shapes: torch.Tensor, programs: torch.Tensor, lengths: torch.Tensor) -> float:
    """Loss with the next row's visual prefix minus loss with the own one, nats/token (eval mode, restored after).

    shapes (N, *s), programs (N, L) 0-padded, lengths (N,); N >= 2.
    """
    if len(shapes) < 2:
        raise ValueError("prefix_gap needs at least two shapes")
    was_training = model.training
    model.eval()
    try:
        prefix = model.encode(shapes)                                 # (N, P, d)
        own, _ = model.loss(shapes, programs, lengths, prefix=prefix)
        other, _ = model.loss(shapes, programs, lengths, prefix=prefix.roll(1, dims=0))
    finally:
        model.train(was_training)
    return float(other - own)


__all__ = ["prefix_gap"]
