"""Length-bucketed batches: less padding, the same per-token loss.

A training batch is padded to its longest program, so a batch mixing a
10-token and a 95-token program spends most of the decoder's work on
padding. Bucketing draws a *pool* of several batches' worth of examples at
once, sorts the pool by program length and cuts it into batches, which are
then used in random order: every example of the pool is still used exactly
once, but each batch holds programs of similar length. The loss stays the
mean cross-entropy over the batch's real tokens (padding never enters it,
:meth:`plad.model.network.PLADNet.loss`), and :func:`trim` drops the columns past
the longest program, which no real token can attend to (attention is
causal), so the loss of a batch does not depend on how much it is padded.

The functions take examples, not a data source, so that any sampler
(pretraining's permutation, a curriculum, the PLAD sources) can bucket
what it draws.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np
import torch

Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]   # shapes (N, *s), programs (N, L), lengths (N,)


def bucket_batches(lengths: np.ndarray, batch_size: int, rng: np.random.Generator | None = None) -> list[np.ndarray]:
    """Positions 0..n-1 of a pool of examples with program ``lengths`` (n,), in batches of ``batch_size`` of
    similar length (the last one shorter when n is not a multiple), in random order when ``rng`` is given.

    Equal lengths keep their order in the pool (a stable sort), so a shuffled pool gives shuffled buckets.
    """
    order = np.argsort(np.asarray(lengths), kind="stable")
    batches = [order[i:i + batch_size] for i in range(0, len(order), batch_size)]
    if rng is not None and len(batches) > 1:
        batches = [batches[i] for i in rng.permutation(len(batches))]
    return batches


def bucketed(batches: Iterable[np.ndarray], lengths: np.ndarray, pool: int,
             rng: np.random.Generator) -> Iterator[np.ndarray]:
    """A stream of index batches (any sampler's: a permutation, a curriculum) regrouped by program length:
    every ``pool`` batches are pooled and cut again by :func:`bucket_batches` (``lengths``: of every example,
    by index). ``pool`` 1 passes the stream through unchanged; a last incomplete pool is not used."""
    if pool <= 1:
        yield from batches
        return
    held: list[np.ndarray] = []
    for batch in batches:
        held.append(np.asarray(batch))
        if len(held) == pool:
            idx = np.concatenate(held)
            held = []
            for b in bucket_batches(lengths[idx], len(idx) // pool, rng):
                yield idx[b]


def trim(programs: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """Programs (N, L) without the columns past the longest program (at least one column)."""
    return programs[:, : max(int(lengths.max()), 1)] if len(lengths) else programs


def trim_batch(batch: Batch) -> Batch:
    shapes, programs, lengths = batch
    return shapes, trim(programs, lengths), lengths


def split_batch(batch: Batch, batch_size: int, rng: np.random.Generator | None = None) -> list[Batch]:
    """A pool drawn as one batch -> batches of ``batch_size`` by program length (:func:`bucket_batches`), trimmed."""
    shapes, programs, lengths = batch
    out = []
    for idx in bucket_batches(lengths.cpu().numpy(), batch_size, rng):
        i = torch.from_numpy(idx).to(lengths.device)
        out.append(trim_batch((shapes[i], programs[i], lengths[i])))
    return out


def padding_share(batches: list[np.ndarray], width: int | None = None) -> float:
    """Share of padding in batches of these program lengths, each padded to its longest (or to ``width``)."""
    total = sum(len(x) * (width or int(x.max())) for x in batches if len(x))
    return 1 - sum(int(x.sum()) for x in batches) / max(total, 1)


__all__ = ["Batch", "bucket_batches", "bucketed", "padding_share", "split_batch", "trim", "trim_batch"]
