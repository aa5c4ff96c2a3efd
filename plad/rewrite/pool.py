"""Search and refinement of many shapes in chunks, by a pool of worker processes.

A :class:`Chunk` is a contiguous run of shapes (their targets, and for
refinement their starting programs); :func:`run_chunks` hands the chunks to
``workers`` processes (spawned, each with one OpenMP/torch thread, so that
W workers use W cores whatever the parent's thread settings) and yields each
finished chunk's :class:`ChunkResult` as it arrives, so that the caller can
write it to disk at once and a killed run redoes only unfinished chunks. With
one worker the chunks run in this process (one torch thread for the
duration). The job is named by the domain's registry name and plain data,
so it pickles cheaply.
"""
from __future__ import annotations

import io
import multiprocessing
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from plad.fsutil import atomic_write, savez

#: what a chunk does: search from scratch, or refine given programs
KINDS = ("search", "refine")


@dataclass
class Chunk:
    """Shapes ``index`` (into the caller's list) with targets (n, *shape) bool and, to refine, their programs."""

    index: np.ndarray
    targets: np.ndarray
    programs: list[list[int]] | None = None


@dataclass
class ChunkResult:
    """The chunk's shapes, the programs found (token lists), their values (n,) float64, their executions
    (n, *shape) bool, the starting values (refine; the metric's worst for search), the worker's seconds and
    whether the time limit cut the chunk's work short (:attr:`plad.rewrite.driver.Result.stopped_by_time`)."""

    index: np.ndarray
    programs: list[list[int]]
    values: np.ndarray
    executions: np.ndarray
    before: np.ndarray
    seconds: float
    stopped_by_time: bool = False


def _run(job: tuple[str, str, dict[str, Any], float | None, Chunk]) -> ChunkResult:
    import torch

    from plad.domains import get_domain
    from plad.rewrite.driver import refine, search, search_config
    from plad.rewrite.evaluate import Scorer

    domain_name, kind, overrides, time_limit, chunk = job
    domain = get_domain(domain_name)
    targets = torch.from_numpy(np.asarray(chunk.targets, dtype=bool))
    start = time.perf_counter()
    if kind == "search":
        cfg = search_config(domain, **overrides)
        # one batch per chunk, so that the time limit (per batch) is the chunk's; without one, the configuration's
        cfg.refine.batch = max(1, len(targets))
        if time_limit is not None:
            cfg.refine.time_limit = time_limit
        result = search(domain, targets, cfg)
        before = np.full(len(targets), float(domain.metric.worst))
    else:
        cfg = refine_config(overrides)
        cfg.batch = max(1, len(targets))
        if time_limit is not None:
            cfg.time_limit = time_limit
        assert chunk.programs is not None
        before = Scorer(domain, targets).values(chunk.programs).numpy()
        result = refine(domain, chunk.programs, targets, cfg)
    executions = Scorer(domain, targets).outputs(result.programs).numpy()
    return ChunkResult(np.asarray(chunk.index), result.programs, result.values.numpy(), executions, before,
                       time.perf_counter() - start, result.stopped_by_time)


def refine_config(overrides: dict[str, Any] | None):
    """:class:`~plad.rewrite.driver.RefineConfig` with ``overrides`` (an unknown key is a ConfigError)."""
    from plad.config import build
    from plad.rewrite.driver import RefineConfig

    return build(RefineConfig, dict(overrides or {}), "refine", source="refine configuration")


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


def split(n: int, size: int) -> list[np.ndarray]:
    """Indices 0..n-1 in contiguous chunks of at most ``size``."""
    size = max(1, int(size))
    return [np.arange(s, min(n, s + size)) for s in range(0, n, size)]


def run_chunks(domain: str, kind: str, chunks: Sequence[Chunk], overrides: dict[str, Any] | None = None,
               workers: int = 1, time_limit: float | None = None) -> Iterator[ChunkResult]:
    """Search (``kind="search"``) or refine (``"refine"``) every chunk; yields results as chunks finish.

    ``overrides``: the search configuration's (:func:`plad.rewrite.search_config`) or the refine
    configuration's; ``time_limit``: seconds per chunk (None: the configuration's ``time_limit``, which is
    then per chunk too).
    """
    if kind not in KINDS:
        raise ValueError(f"chunk kind {kind!r}: expected one of {', '.join(KINDS)}")
    jobs = [(domain, kind, dict(overrides or {}), time_limit, c) for c in chunks]
    if not jobs:
        return
    workers = max(1, min(int(workers), len(jobs)))
    if workers == 1:
        from plad.device import torch_threads

        with torch_threads(1):
            for job in jobs:
                yield _run(job)
        return
    # spawn, not fork: a parent that has run OpenMP regions (training) cannot safely fork workers that use
    # them; the children read OMP_NUM_THREADS when they import torch, so it is set while they start
    old = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_init_worker)
    finally:
        if old is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = old
    with pool:
        yield from pool.imap_unordered(_run, jobs)


# -- chunk files: a finished chunk on disk, so that a killed run redoes only unfinished chunks --------------
def chunk_file(folder: Path, i: int) -> Path:
    """The file of chunk ``i`` in ``folder``."""
    return folder / f"chunk_{i:05d}.npz"


def pad_programs(programs: list[list[int]], width: int) -> np.ndarray:
    out = np.full((len(programs), width), -1, dtype=np.int16)
    for k, p in enumerate(programs):
        out[k, : len(p)] = p
    return out


def unpad_programs(rows: np.ndarray) -> list[list[int]]:
    return [r[r >= 0].tolist() for r in rows]


def write_chunk(path: Path, r: ChunkResult, width: int) -> None:
    buf = io.BytesIO()
    savez(buf, index=r.index, programs=pad_programs(r.programs, width), values=r.values, before=r.before,
                        executions=np.packbits(r.executions.reshape(len(r.index), -1), axis=1),
                        seconds=np.asarray(r.seconds), stopped_by_time=np.asarray(r.stopped_by_time))
    atomic_write(path, lambda fh: fh.write(buf.getvalue()))


def read_chunk(path: Path, shape: tuple[int, ...]) -> ChunkResult:
    with np.load(path) as z:
        n = len(z["index"])
        executions = np.unpackbits(z["executions"], axis=1, count=int(np.prod(shape))).astype(bool)
        # chunk files written before the flag existed: not known to be cut short
        timed = bool(z["stopped_by_time"]) if "stopped_by_time" in z.files else False
        return ChunkResult(z["index"].copy(), unpad_programs(z["programs"]), z["values"].copy(),
                           executions.reshape(n, *shape), z["before"].copy(), float(z["seconds"]), timed)


class Refined(NamedTuple):
    """What :func:`refine_all` returns, in the input order."""

    programs: list[list[int]]
    values: np.ndarray         # (N,)
    executions: np.ndarray     # (N, *shape) bool
    #: a chunk's time limit cut its work short (the programs then depend on the machine's speed)
    stopped_by_time: bool


def refine_all(domain: str, programs: Sequence[Sequence[int]], targets: np.ndarray,
               overrides: dict[str, Any] | None = None, workers: int = 1,
               chunk: int | None = None) -> Refined:
    """Refine ``programs[i]`` towards ``targets[i]`` for all i (:class:`Refined`); no program comes back worse.
    ``chunk`` (default: the refine batch) shapes per job."""
    size = chunk or refine_config(overrides).batch
    chunks = [Chunk(c, targets[c], [list(programs[i]) for i in c]) for c in split(len(programs), size)]
    out_programs: list[list[int]] = [[] for _ in range(len(programs))]
    values = np.zeros(len(programs))
    executions = np.zeros((len(programs), *targets.shape[1:]), dtype=bool)
    timed = False
    for r in run_chunks(domain, "refine", chunks, overrides, workers):
        for k, i in enumerate(r.index):
            out_programs[int(i)] = r.programs[k]
        values[r.index] = r.values
        executions[r.index] = r.executions
        timed |= r.stopped_by_time
    return Refined(out_programs, values, executions, timed)
