"""PLAD methods: a method's params entry and the (X, Z) sources the mixtures train on.

A PLAD method is a mixture of sources of (shape, program) pairs, each a plugin of
:mod:`plad.learn.method_registry`; the built-in ones:

* ``st``   self-training: (real training shape, its best program in P_BEST) (:data:`ST`);
* ``lest`` latent execution self-training: (execution of that program, program) (:data:`LEST`);
* ``ws``   wake-sleep: (execution of a program sampled from a generative model, program)
  (:data:`plad.learn.rounds.WS`).

Mixtures are written with ``+`` and optional weights, e.g. ``lest+st`` or
``lest:2+st:1+ws:1`` (:func:`plad.learn.method_registry.parse_mixture`). Each batch
is drawn whole from one source, chosen at random with the normalized weights.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from plad.data.batching import split_batch, trim_batch
from plad.device import to_device
from plad.domains.base import split_padding
from plad.learn.job import Job
from plad.learn.method_registry import Mixture, PairSource, parse_mixture
from plad.learn.pbest import PBest

Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]   # shapes (N, *s), programs (N, L), lengths (N,)
Source = Callable[[np.random.Generator, int], Batch]


@dataclass
class PBestSearchConfig:
    """Search beside learning (params ``finetune.<domain>.methods.<key>.search``): P_BEST seeded by search
    from scratch before the first round's training, and a share of it rewritten after each round's inference
    (:mod:`plad.learn.pbest_search`)."""

    #: share of the training shapes searched from scratch in round 1 (0: no seeding)
    seed_share: float = 1.0
    #: wall-clock budget of the seeding, minutes (null: none)
    seed_minutes: float | None = None
    #: search configuration overrides (:func:`plad.rewrite.search_config`, e.g. ``{refine: {rounds: 0}}``)
    seed_config: dict = field(default_factory=dict)
    #: share of the P_BEST entries rewritten after each round's inference (unrefined entries first; 0: none)
    rewrite_share: float = 0.5
    #: wall-clock budget of each round's rewriting, minutes (null: none)
    rewrite_minutes: float | None = None
    #: refine configuration overrides (:class:`plad.rewrite.RefineConfig`, e.g. ``{rounds: 3}``)
    rewrite_config: dict = field(default_factory=dict)
    #: worker processes (one thread each)
    workers: int = 1
    #: shapes per chunk (a chunk is the unit of work of a worker and of resuming)
    chunk: int = 256


@dataclass
class MethodConfig:
    """One fine-tuning method of the comparison (params ``finetune.<domain>.methods.<key>``)."""

    #: a registered method ("rl") or a PLAD mixture of registered sources (st / lest / ws), e.g. "lest+st"
    #: (:mod:`plad.learn.method_registry`)
    method: str = "lest+st"
    #: P_BEST mode of PLAD methods: all-time (the paper's) or per-round (the supplement's ablation); its one home
    pbest_mode: str = "all-time"
    #: search-seeded and rewritten P_BEST (PLAD methods; null: the paper's P_BEST, from inference only)
    search: PBestSearchConfig | None = None
    #: this method's own wall-clock safety net, minutes, instead of the stage's ``max_minutes`` (null: the
    #: stage's)
    max_minutes: float | None = None
    #: this method's rounds, at most ``plad.max_rounds`` (null: that); PLAD methods only (RL's epochs:
    #: ``rl.max_epochs``). The work that fixes a result: the profiles set it per method and domain
    max_rounds: int | None = None


def _pbest_batch(pbest: PBest, shapes: np.ndarray, idx: np.ndarray, device: torch.device) -> Batch:
    programs, lengths = split_padding(torch.from_numpy(pbest.programs[idx].astype(np.int64)))
    return to_device(shapes[idx], device), to_device(programs, device), to_device(lengths, device)


def st_source(pbest: PBest, real: np.ndarray, device: torch.device) -> Source:
    """Self-training: real shapes paired with their best programs (pseudo-labels)."""
    def draw(rng: np.random.Generator, n: int) -> Batch:
        return _pbest_batch(pbest, real, rng.choice(np.nonzero(pbest.has)[0], size=n), device)
    return draw


def lest_source(pbest: PBest, device: torch.device) -> Source:
    """LEST: executions of the best programs paired with those programs (exact labels)."""
    def draw(rng: np.random.Generator, n: int) -> Batch:
        return _pbest_batch(pbest, pbest.executions, rng.choice(np.nonzero(pbest.has)[0], size=n), device)
    return draw


@dataclass
class RoundContext:
    """What a source is built from in round ``rnd`` of the PLAD rounds (:meth:`PairSource.build`)."""

    job: Job
    #: the run's :class:`plad.learn.rounds.RoundsConfig`
    cfg: Any
    #: P_BEST after this round's inference (and search)
    pbest: PBest
    rnd: int
    device: torch.device
    #: seconds left of the run's budget
    remaining: Callable[[], float]
    #: ``step(name, fn, *args)``: runs a step of the round (a task of the Prefect flow)
    step: Callable[..., Any]


class _STSource(PairSource):
    def build(self, ctx: RoundContext) -> tuple[Source, dict[str, float]]:
        return st_source(ctx.pbest, ctx.job.train, ctx.device), {}


class _LESTSource(PairSource):
    def build(self, ctx: RoundContext) -> tuple[Source, dict[str, float]]:
        return lest_source(ctx.pbest, ctx.device), {}


#: the registered ``st`` and ``lest`` sources
ST, LEST = _STSource(), _LESTSource()


def mixture_batches(mixture: Mixture, sources: dict[str, Source], batch_size: int,
                    seed: int, bucket_pool: int = 1) -> Callable[[int], Iterator[Batch]]:
    """``batches(epoch)`` (from 0) for :func:`plad.learn.train.fit`: each batch whole from one source, by weight.

    With ``bucket_pool`` > 1 a source draws that many batches' worth of pairs at once, which are grouped into
    batches by program length (:mod:`plad.data.batching`) and handed out one at a time whenever the source is
    chosen. Batches are cut to their longest program.
    """
    missing = [n for n in mixture.names if n not in sources]
    if missing:
        raise ValueError(f"no data for source(s) {', '.join(missing)}")

    def batches(epoch: int) -> Iterator[Batch]:
        rng = np.random.default_rng([seed, epoch])
        pending: dict[str, list[Batch]] = {name: [] for name in mixture.names}
        while True:
            name = mixture.names[rng.choice(len(mixture.names), p=mixture.weights)]
            if bucket_pool <= 1:
                yield trim_batch(sources[name](rng, batch_size))
                continue
            if not pending[name]:
                pending[name] = split_batch(sources[name](rng, batch_size * bucket_pool), batch_size, rng)
            yield pending[name].pop()
    return batches


# parse_mixture and Mixture are the registry's (they read its sources), here where the mixtures' callers look
__all__ = ["LEST", "ST", "Batch", "MethodConfig", "Mixture", "PBestSearchConfig", "RoundContext", "Source",
           "lest_source", "mixture_batches", "parse_mixture", "st_source"]
