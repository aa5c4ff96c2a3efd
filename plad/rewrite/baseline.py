"""Search-only numbers ("search, no network") on a domain's real shapes.

:func:`run_baseline` runs :func:`plad.rewrite.search` (the domain's default search configuration, with
overrides, e.g. ``effort="best"``) on shapes split into contiguous chunks searched by as many processes
(each with one torch thread), and returns a summary: mean metric, wall seconds per shape, process seconds
per shape, CPU seconds per shape (what the processes really got of the machine), where the time went and the
programs. Every value is the domain metric of the re-executed program (search re-scores its results before
returning). The ``search_only`` stage runs it; ``python -m plad.tools.search_baseline`` is its command line.
"""
from __future__ import annotations

import dataclasses
import multiprocessing
import time
from typing import Any

import numpy as np


def _worker(job: tuple[str, np.ndarray, dict]) -> tuple[list[str], list[float], dict, float, float, bool]:
    import torch

    from plad.domains import get_domain
    from plad.rewrite import search, search_config

    torch.set_num_threads(1)
    name, targets, overrides = job
    domain = get_domain(name)
    cpu = time.process_time()
    result = search(domain, torch.from_numpy(targets), search_config(domain, **overrides))
    return ([domain.format(p) if p else "" for p in result.programs], result.values.tolist(),
            result.stats.as_dict(), result.seconds, time.process_time() - cpu, result.stopped_by_time)


def run_baseline(domain_name: str, targets: np.ndarray, workers: int = 1, overrides: dict | None = None,
                 ) -> dict[str, Any]:
    """Search every target (N, *shape) bool; returns the summary (with the programs under ``programs``)."""
    from plad.domains import get_domain
    from plad.rewrite import search_config

    overrides = dict(overrides or {})
    domain = get_domain(domain_name)
    config = search_config(domain, **overrides)          # checks the overrides before starting workers
    workers = max(1, min(workers, len(targets)))
    chunks = [c for c in np.array_split(targets, workers) if len(c)]
    jobs = [(domain_name, c, overrides) for c in chunks]
    start = time.perf_counter()
    if workers == 1:
        outputs = [_worker(jobs[0])]
    else:
        # fork: the children inherit the loaded modules; each sets one torch thread itself
        with multiprocessing.get_context("fork").Pool(workers) as pool:
            outputs = pool.map(_worker, jobs)
    wall = time.perf_counter() - start
    programs = [p for o in outputs for p in o[0]]
    values = np.array([v for o in outputs for v in o[1]])
    stats: dict[str, Any] = {}
    for o in outputs:
        for k, v in o[2].items():
            if isinstance(v, dict):
                inner = stats.setdefault(k, {})
                for kk, vv in v.items():
                    inner[kk] = inner.get(kk, 0) + vv
            else:
                stats[k] = stats.get(k, 0) + v
    n = len(values)
    return {
        "domain": domain_name, "metric": domain.metric.name, "higher_is_better": domain.metric.higher_is_better,
        "n": n, "mean": float(values.mean()) if n else None, "workers": workers,
        "seconds": wall, "seconds_per_shape": wall / max(n, 1),
        "process_seconds_per_shape": sum(o[3] for o in outputs) / max(n, 1),
        # CPU time actually used: on a shared machine, wall time also counts waiting for a core
        "cpu_seconds_per_shape": sum(o[4] for o in outputs) / max(n, 1),
        "mean_tokens": float(np.mean([len(domain.parse(p)) if p else 0 for p in programs])) if n else None,
        "empty_programs": sum(1 for p in programs if not p),
        # a configured time limit cut some search short (none by default: the search's work is fixed)
        "stopped_by_time": any(o[5] for o in outputs),
        "config": dataclasses.asdict(config), "stats": stats, "programs": programs, "values": values.tolist(),
    }
