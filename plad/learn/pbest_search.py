"""Search beside learning: P_BEST seeded by search and rewritten after each round's inference.

A PLAD method with a ``search`` block (:class:`plad.learn.methods.PBestSearchConfig`)
gets two extra steps in its rounds, both after the round's beam inference
and before its training (:attr:`plad.learn.rounds.RoundHooks.after_infer`):

* **seeding** (round 1 only): search from scratch (:func:`plad.rewrite.search`)
  on ``seed_share`` of the training shapes within ``seed_minutes``;
* **rewriting** (every round): refine (:func:`plad.rewrite.refine`)
  ``rewrite_share`` of the P_BEST entries within ``rewrite_minutes``,
  entries not refined since they last changed first.

The work of both is fixed by the shares and the search and refine
configurations; the minutes are a safety net, shared equally by a step's
chunks. A step whose chunk ran out of its share says so
(``<step>_stopped_by_time`` in the round's history), and so does the run's
summary.

Found programs are offered to P_BEST like inferred ones: an entry changes
only for a program at least as good (and the rewriters never return a
worse one), so neither step makes an entry worse. Rewritten entries are
marked refined. The work is split into chunks run by a pool of worker
processes (:mod:`plad.rewrite.pool`); each finished chunk is written
atomically under ``<run>/search/`` (``seed/`` and ``rewrite_<round>/``), so a
killed run, started again, applies the finished chunks from disk and
searches only the rest. Each step reports the share of its shapes whose
entry got strictly better, the mean gain (in the metric's better direction)
and its seconds, as columns of the round's history row (and so MLflow
metrics of the round).
"""
from __future__ import annotations

import io
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plad.config import ConfigError
from plad.fsutil import atomic_write, savez
from plad.learn import distributed as dist
from plad.learn.methods import PBestSearchConfig
from plad.learn.pbest import PBest
from plad.rewrite.pool import (
    Chunk,
    chunk_file,
    pad_programs,
    read_chunk,
    refine_config,
    run_chunks,
    split,
    unpad_programs,
    write_chunk,
)

SEARCH_DIR = "search"
PLAN = "plan.npz"


def check(cfg: PBestSearchConfig, domain, where: str) -> None:
    """Fail early (ConfigError naming ``where``) on a bad share, budget or rewriter configuration."""
    from plad.rewrite import search_config
    from plad.rewrite.driver import check_refine

    for name in ("seed_share", "rewrite_share"):
        v = getattr(cfg, name)
        if not 0.0 <= v <= 1.0:
            raise ConfigError(f"{where}.{name} = {v}: expected a share between 0 and 1")
    for name in ("seed_minutes", "rewrite_minutes"):
        v = getattr(cfg, name)
        if v is not None and not v > 0:
            raise ConfigError(f"{where}.{name} = {v}: expected a positive number of minutes, or null")
    if cfg.workers < 1 or cfg.chunk < 1:
        raise ConfigError(f"{where}: workers ({cfg.workers}) and chunk ({cfg.chunk}) must be at least 1")
    if domain.rewrite is None:
        raise ConfigError(f"{where}: the {domain.name} domain has no search support")
    for name, build in (("seed_config", lambda c: search_config(domain, **c)),
                        ("rewrite_config", lambda c: check_refine(domain, refine_config(c)))):
        try:
            build(getattr(cfg, name))
        except (ConfigError, TypeError, ValueError) as err:
            raise ConfigError(f"{where}.{name}: {err}") from None


@dataclass
class StepStats:
    shapes: int
    improved: float      # share of the step's shapes whose entry got strictly better
    gain: float          # mean gain of those shapes' entries, in the metric's better direction
    seconds: float       # wall-clock seconds of the step (this process, including resumed chunks' reading)
    chunks_resumed: int  # chunks read from disk instead of computed
    #: a chunk's share of the step's minutes cut its work short (see plad.rewrite.driver.Result)
    stopped_by_time: bool = False

    def row(self, prefix: str) -> dict[str, float]:
        return {f"{prefix}_shapes": float(self.shapes), f"{prefix}_improved": self.improved,
                f"{prefix}_gain": self.gain, f"{prefix}_seconds": self.seconds,
                f"{prefix}_chunks_resumed": float(self.chunks_resumed),
                f"{prefix}_stopped_by_time": float(self.stopped_by_time)}


class PBestSearch:
    """The seeding and rewriting steps of one fine-tuning run (``out``: the run's folder)."""

    def __init__(self, domain, cfg: PBestSearchConfig, out: Path, seed: int = 0):
        self.domain, self.cfg, self.seed = domain, cfg, seed
        self.folder = Path(out) / SEARCH_DIR
        self.metric = domain.metric

    # -- the hook -------------------------------------------------------------------------------
    def after_infer(self, rnd: int, pbest: PBest, shapes: np.ndarray) -> dict[str, float]:
        """Seed (round 1) and rewrite P_BEST in place; the round history's columns."""
        row: dict[str, float] = {}
        if rnd == 1 and self.cfg.seed_share > 0:
            row.update(self.seed_pbest(pbest, shapes).row("seed"))
        if self.cfg.rewrite_share > 0:
            row.update(self.rewrite_pbest(rnd, pbest, shapes).row("rewrite"))
        return row

    # -- steps ----------------------------------------------------------------------------------
    def seed_plan(self, n: int) -> np.ndarray:
        """The training shapes searched from scratch: a fixed random ``seed_share`` of them, sorted."""
        k = math.ceil(self.cfg.seed_share * n)
        return np.sort(np.random.default_rng([self.seed, 17]).permutation(n)[:k])

    def rewrite_plan(self, pbest: PBest, rnd: int) -> np.ndarray:
        """``rewrite_share`` of the filled entries: not yet refined first, each group in a random order."""
        rng = np.random.default_rng([self.seed, 31, rnd])
        filled = np.nonzero(pbest.has)[0]
        k = math.ceil(self.cfg.rewrite_share * len(filled))
        fresh, done = filled[~pbest.refined[filled]], filled[pbest.refined[filled]]
        return np.concatenate([rng.permutation(fresh), rng.permutation(done)])[:k].astype(np.int64)

    def seed_pbest(self, pbest: PBest, shapes: np.ndarray) -> StepStats:
        index = self.seed_plan(len(shapes))
        chunks = [Chunk(index[c], shapes[index[c]]) for c in split(len(index), self.cfg.chunk)]
        return self._step(self.folder / "seed", "search", chunks, self.cfg.seed_config, self.cfg.seed_minutes,
                          pbest, refined=False)

    def rewrite_pbest(self, rnd: int, pbest: PBest, shapes: np.ndarray) -> StepStats:
        folder = self.folder / f"rewrite_{rnd:03d}"
        plan_file = folder / PLAN
        if dist.broadcast(plan_file.exists()):   # a resumed round rewrites the very entries it chose before
            with np.load(plan_file) as z:
                index, starts = z["index"].copy(), unpad_programs(z["programs"])
        else:
            index = self.rewrite_plan(pbest, rnd)
            starts = [pbest.program(int(i)) for i in index]
            if dist.is_main():
                buf = io.BytesIO()
                savez(buf, index=index, programs=pad_programs(starts, pbest.programs.shape[1]))
                atomic_write(plan_file, lambda fh: fh.write(buf.getvalue()))
        chunks = [Chunk(index[c], shapes[index[c]], [starts[j] for j in c]) for c in split(len(index), self.cfg.chunk)]
        return self._step(folder, "refine", chunks, self.cfg.rewrite_config, self.cfg.rewrite_minutes, pbest,
                          refined=True)

    def _step(self, folder: Path, kind: str, chunks: list[Chunk], overrides: dict, minutes: float | None,
              pbest: PBest, refined: bool) -> StepStats:
        start = time.perf_counter()
        results = self._results(folder, kind, chunks, overrides, minutes, pbest.programs.shape[1])
        resumed = results.pop()
        index = np.concatenate([r.index for r in results]) if results else np.zeros(0, np.int64)
        old = pbest.values[index].copy()
        for r in results:
            pbest.update(r.index, r.programs, r.values, r.executions, refined=refined)
        new = pbest.values[index]
        sign = 1.0 if self.metric.higher_is_better else -1.0
        had = ~np.isnan(old)
        delta = sign * (new - np.nan_to_num(old))          # > 0: better (only meaningful where ``had``)
        better = np.where(had, delta > 0, ~np.isnan(new))   # an empty entry filled counts as improved
        gain = float(delta[had].mean()) if had.any() else 0.0
        return StepStats(len(index), float(better.mean()) if len(index) else 0.0, gain,
                         time.perf_counter() - start, resumed, any(r.stopped_by_time for r in results))

    def _results(self, folder: Path, kind: str, chunks: list[Chunk], overrides: dict, minutes: float | None,
                 width: int) -> list:
        """Every chunk's result, read from disk where a previous run finished it; the last item: how many."""
        if not dist.is_main():   # rank 0 searches; every rank applies the same results
            return dist.broadcast(None)
        shape = tuple(self.domain.shape)
        done = {i: read_chunk(chunk_file(folder, i), shape) for i in range(len(chunks))
                if chunk_file(folder, i).exists()}
        todo = [i for i in range(len(chunks)) if i not in done]
        resumed = len(done)
        # the step's budget shared by its chunks: W workers each run about len/W chunks in turn
        limit = None if minutes is None else minutes * 60 * max(1, self.cfg.workers) / max(1, len(chunks))
        by_first = {int(chunks[i].index[0]): i for i in todo}
        for r in run_chunks(self.domain.name, kind, [chunks[i] for i in todo], overrides, self.cfg.workers, limit):
            i = by_first[int(r.index[0])]
            write_chunk(chunk_file(folder, i), r, width)
            done[i] = r
        out = [done[i] for i in range(len(chunks))]
        out.append(resumed)
        if dist.world() > 1:
            dist.broadcast(out)
        return out

