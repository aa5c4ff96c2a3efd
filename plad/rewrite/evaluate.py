"""Batched scoring of candidate programs, shared by all rewriters.

A :class:`Scorer` holds one batch of targets. Every rewriter hands it all
candidates of all its programs at once (:class:`~plad.domains.space.Candidates`,
each row tagged with the program it is for) and gets back, per program, the
best candidate: the domain's screen (if any) keeps the ``screen_keep`` best
of each program's candidates, then the kept ones are executed by the domain's
executor and scored by the domain's metric, in large chunks.

The objective is the domain metric (its ``higher_is_better`` decides), ties
going to fewer tokens; a rewriter accepts a candidate only if it beats the
current program under that order (:func:`improves`), so no rewrite ever makes
a program worse.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from plad.domains.space import Candidates

if TYPE_CHECKING:  # pragma: no cover
    from plad.domains.base import Domain

#: rows executed and scored per call of the domain's executor and metric (memory bound)
EXACT_CHUNK = 2048
#: rows per call of the screen
SCREEN_CHUNK = 8192


@dataclass
class Stats:
    """Where a rewriter's time went, and how many candidates each stage saw."""

    screen_exec: float = 0.0      # seconds executing candidates for the screen
    screen_score: float = 0.0     # seconds in the screen's cheap score
    exec: float = 0.0             # seconds in the domain's executor (exact scoring)
    metric: float = 0.0           # seconds in the domain's metric
    screened: int = 0             # candidates screened
    scored: int = 0               # candidates executed and scored exactly
    counts: dict[str, int] = field(default_factory=dict)  # accepted rewrites per rewriter

    def add(self, other: Stats) -> None:
        for name in ("screen_exec", "screen_score", "exec", "metric", "screened", "scored"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for k, v in other.counts.items():
            self.counts[k] = self.counts.get(k, 0) + v

    def accepted(self, rewriter: str, n: int) -> None:
        self.counts[rewriter] = self.counts.get(rewriter, 0) + int(n)

    def as_dict(self) -> dict:
        return {"screen_exec_s": self.screen_exec, "screen_score_s": self.screen_score, "exec_s": self.exec,
                "metric_s": self.metric, "screened": self.screened, "scored": self.scored,
                "accepted": dict(self.counts)}


def oriented(values: torch.Tensor, higher_is_better: bool) -> torch.Tensor:
    """Values turned so that lower is better."""
    return -values if higher_is_better else values


def improves(new_value: torch.Tensor, new_length: torch.Tensor, value: torch.Tensor, length: torch.Tensor,
             higher_is_better: bool) -> torch.Tensor:
    """Elementwise: (new_value, new_length) strictly better than (value, length) under the objective."""
    a, b = oriented(new_value, higher_is_better), oriented(value, higher_is_better)
    return (a < b) | ((a == b) & (new_length < length))


def first_per_group(owner: np.ndarray, *keys: np.ndarray) -> np.ndarray:
    """Row of each group's smallest (keys[0], keys[1], ...) (ties: the first row); -1 for empty groups.

    Returns (n_groups,) where n_groups = owner.max() + 1.
    """
    n = int(owner.max()) + 1 if len(owner) else 0
    order = np.lexsort(tuple(reversed(keys)) + (owner,)) if keys else np.argsort(owner, kind="stable")
    firsts = np.ones(len(order), dtype=bool)
    firsts[1:] = owner[order][1:] != owner[order][:-1]
    out = np.full(n, -1, dtype=np.int64)
    out[owner[order][firsts]] = order[firsts]
    return out


def top_per_group(score: np.ndarray, lengths: np.ndarray, owner: np.ndarray, keep: int) -> np.ndarray:
    """Rows of the ``keep`` highest scores of each group (ties: fewer tokens, then the first row), sorted."""
    order = np.lexsort((np.arange(len(score)), lengths, -score, owner))
    grouped = owner[order]
    starts = np.ones(len(order), dtype=bool)
    starts[1:] = grouped[1:] != grouped[:-1]
    start_of = np.maximum.accumulate(np.where(starts, np.arange(len(order)), 0))
    rank = np.arange(len(order)) - start_of
    return np.sort(order[rank < keep])


class Scorer:
    """Scores programs of one batch of targets with the domain's executor and metric.

    targets: (N, *shape) bool. Program ``i`` and candidates with owner ``i``
    are scored against ``targets[i]``.
    """

    def __init__(self, domain: Domain, targets: torch.Tensor, screen: bool = True):
        if domain.rewrite is None:
            raise ValueError(f"the {domain.name} domain has no search support (its rewrite member is None)")
        self.domain = domain
        self.space = domain.rewrite
        self.metric = domain.metric
        self.targets = targets.to(torch.bool).cpu()
        self.stats = Stats()
        #: use the domain's screen (False: every candidate is scored exactly; a slow baseline)
        self.use_screen = screen
        self._screen_prepared = None

    @property
    def higher_is_better(self) -> bool:
        return self.metric.higher_is_better

    # ---- exact -------------------------------------------------------------------------------
    def outputs(self, programs: Sequence[Sequence[int]]) -> torch.Tensor:
        """Executions (B, *shape) bool of programs; the empty program executes to nothing."""
        out = torch.zeros(len(programs), *self.domain.shape, dtype=torch.bool)
        rows = [i for i, p in enumerate(programs) if len(p)]
        if rows:
            c = Candidates.from_lists([programs[i] for i in rows], rows)
            t0 = time.perf_counter()
            out[rows] = self.domain.execute(c.tokens).cpu()
            self.stats.exec += time.perf_counter() - t0
        return out

    def values(self, programs: Sequence[Sequence[int]], owner: Sequence[int] | None = None) -> torch.Tensor:
        """Exact metric (B,) float64 of program k against target ``owner[k]`` (default: target k);
        the empty program scores the worst value."""
        owner = list(range(len(programs))) if owner is None else list(owner)
        values = torch.full((len(programs),), float(self.metric.worst), dtype=torch.float64)
        rows = [k for k, p in enumerate(programs) if len(p)]
        if rows:
            c = Candidates.from_lists([programs[k] for k in rows], [owner[k] for k in rows])
            values[rows] = self.exact(c.tokens, c.owner)
        return values

    def exact(self, tokens: torch.Tensor, owner: torch.Tensor) -> torch.Tensor:
        """Exact metric (C,) float64 of candidate rows against ``targets[owner]``."""
        C = tokens.shape[0]
        values = torch.empty(C, dtype=torch.float64)
        if C == 0:
            return values
        # rows of the same target next to each other, so that a metric with per-target
        # preparation (e.g. Chamfer's target distance maps) prepares each target once per chunk
        order = torch.argsort(owner, stable=True)
        for start in range(0, C, EXACT_CHUNK):
            rows = order[start:start + EXACT_CHUNK]
            t0 = time.perf_counter()
            out = self.domain.execute(tokens[rows]).cpu()
            t1 = time.perf_counter()
            values[rows] = self._metric(out, owner[rows])
            self.stats.exec += t1 - t0
            self.stats.metric += time.perf_counter() - t1
            self.stats.scored += len(rows)
        return values

    def _metric(self, out: torch.Tensor, owner: torch.Tensor) -> torch.Tensor:
        """Metric of outputs (M, *shape) against targets[owner] (owner sorted)."""
        if self.metric.prepare is None:
            return self.metric(out, self.targets[owner])
        # rectangular (G, K) layout: G targets, K candidates each (short groups padded
        # with copies of their first row), so the metric prepares each target once
        groups, inverse, counts = torch.unique_consecutive(owner, return_inverse=True, return_counts=True)
        K = int(counts.max())
        starts = torch.cumsum(counts, 0) - counts
        rank = torch.arange(len(owner)) - starts[inverse]
        index = starts[:, None] + torch.minimum(torch.arange(K)[None, :], counts[:, None] - 1)   # (G, K)
        scores = self.metric.score_candidates(out[index], self.targets[groups])                   # (G, K)
        return scores[inverse, rank]

    # ---- screen + exact ----------------------------------------------------------------------
    def screen(self, cands: Candidates) -> torch.Tensor:
        """The domain's cheap score (C,) of every candidate (higher is better)."""
        if self._screen_prepared is None:
            self._screen_prepared = self.space.prepare_screen(self.targets)
        C = len(cands)
        scores = torch.empty(C, dtype=torch.float64)
        for start in range(0, C, SCREEN_CHUNK):
            sl = slice(start, start + SCREEN_CHUNK)
            t0 = time.perf_counter()
            out = self.space.screen_run(cands[sl])
            t1 = time.perf_counter()
            scores[sl] = self.space.screen_score(out, cands.owner[sl], self._screen_prepared).double()
            self.stats.screen_exec += t1 - t0
            self.stats.screen_score += time.perf_counter() - t1
        self.stats.screened += C
        return scores

    def top(self, cands: Candidates, group: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` best candidates of each group (group: (C,) int, e.g. the beam entry a candidate extends;
        the target is still ``cands.owner``): (rows (M,) long, their exact values (M,) float64), ordered by
        group, then metric, then fewer tokens, then row.

        With a domain screen (and ``use_screen``), only each group's ``max(screen_keep, k)`` best by the
        cheap score are scored exactly.
        """
        rows = np.arange(len(cands))
        lengths = cands.lengths.numpy()
        keep = self.space.screen_keep
        if (self.use_screen and keep is not None and len(cands)
                and np.bincount(group).max() > max(keep, k)):
            rows = top_per_group(self.screen(cands).numpy(), lengths, group, max(keep, k))
        values = self.exact(cands.tokens[rows], cands.owner[rows]).numpy()
        # top_per_group keeps the k highest scores: the metric turned so that higher is better
        pick = top_per_group(-oriented(torch.from_numpy(values), self.higher_is_better).numpy(), lengths[rows],
                             group[rows], k)
        order = np.lexsort((rows[pick], lengths[rows][pick],
                            oriented(torch.from_numpy(values[pick]), self.higher_is_better).numpy(), group[rows][pick]))
        pick = pick[order]
        return rows[pick], values[pick]

    def best(self, cands: Candidates, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Best candidate of each of ``n`` programs: (row (n,) long, -1 where a program has no
        candidate; its exact value (n,) float64, the worst value where none).

        Order: metric, then fewer tokens, then the first row. With a domain
        screen (and ``use_screen``), only each program's ``screen_keep`` best by
        the cheap score are scored exactly.
        """
        rows = np.arange(len(cands))
        owner = cands.owner.numpy()
        lengths = cands.lengths.numpy()
        keep = self.space.screen_keep
        if self.use_screen and keep is not None and len(cands) and np.bincount(owner, minlength=n).max() > keep:
            rows = top_per_group(self.screen(cands).numpy(), lengths, owner, keep)
        values = self.exact(cands.tokens[rows], cands.owner[rows]).numpy()
        best = np.full(n, -1, dtype=np.int64)
        best_values = np.full(n, float(self.metric.worst))
        if len(rows):
            pick = first_per_group(owner[rows], oriented(torch.from_numpy(values), self.higher_is_better).numpy(),
                                   lengths[rows])
            has = pick >= 0
            best[: len(pick)][has] = rows[pick[has]]
            best_values[: len(pick)][has] = values[pick[has]]
        return torch.from_numpy(best), torch.from_numpy(best_values)
