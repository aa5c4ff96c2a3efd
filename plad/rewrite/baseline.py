"""Search-only numbers ("search, no network") on a domain's real shapes.

Usage::

    python -m plad.rewrite.baseline DOMAIN [--split test] [--limit N | --spaced N] [--workers W]
        [--prepared data/prepared] [--set KEY=VALUE ...] [--out FILE.json]

Runs :func:`plad.rewrite.search` (the domain's default search configuration,
with ``--set`` overrides, e.g. ``--set effort=best``) on the prepared shapes of a split (all,
the first ``--limit``, or ``--spaced`` N evenly spaced over it as the stages' ``limit``), split into
``--workers`` contiguous chunks searched by as many processes (each with one
torch thread), and prints a summary: mean metric, wall seconds per shape,
process seconds per shape, CPU seconds per shape (what the processes really
got of the machine) and where the time went. With ``--out`` the
summary is written as JSON and the programs (one per line, in shape order)
beside it as ``<out>.programs.txt``. Every value is the domain metric of the
re-executed program (search re-scores its results before returning).
"""
from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
import os
import sys
import time
from pathlib import Path
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


def main(argv: list[str] | None = None) -> int:
    import json

    import yaml

    from plad.config import ConfigError
    from plad.data.files import load_prepared, load_split
    from plad.domains import get_domain
    from plad.fsutil import atomic_write_text
    from plad.rewrite import search_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain")
    parser.add_argument("--split", default="test")
    parser.add_argument("--limit", type=int, default=None, help="first N shapes only")
    parser.add_argument("--spaced", type=int, default=None,
                        help="N shapes evenly spaced over the split (as the stages' limit)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--prepared", default="data/prepared", help="folder of the prepared <domain>.npz")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", default=None, help="summary JSON (programs beside it)")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

    overrides = {}
    for item in args.set:
        key, _, text = item.partition("=")
        overrides[key.strip()] = yaml.safe_load(text)
    try:    # a bad --set: one line before any work, not a traceback
        search_config(get_domain(args.domain), **overrides)
    except ConfigError as err:
        print(err, file=sys.stderr)
        return 1
    path = Path(args.prepared) / f"{args.domain}.npz"
    if not path.is_file():
        print(f"{path}: no such prepared dataset (run the prepare stages first)", file=sys.stderr)
        return 1
    if args.spaced is not None and args.limit is not None:
        print("--limit and --spaced: give one of them", file=sys.stderr)
        return 2
    if args.spaced is not None:
        targets = load_split(path, args.split, args.spaced)[0]
    else:
        targets = load_prepared(path, args.split)[: args.limit]
    summary = run_baseline(args.domain, targets, args.workers, overrides)
    programs = summary.pop("programs")
    values = summary.pop("values")
    print(f"{args.domain} {args.split}: {summary['n']} shapes, mean {summary['metric']} {summary['mean']:.4f}, "
          f"{summary['seconds_per_shape']:.3f} s per shape wall ({summary['workers']} workers), "
          f"{summary['process_seconds_per_shape']:.3f} s per shape per process, "
          f"{summary['cpu_seconds_per_shape']:.3f} CPU s per shape, "
          f"{summary['mean_tokens']:.1f} tokens")
    print(json.dumps(summary["stats"]))
    if args.out:
        out = Path(args.out)
        atomic_write_text(out, json.dumps(summary, indent=2) + "\n")
        atomic_write_text(out.with_suffix(".programs.txt"),
                          "".join(f"{p}\t{v!r}\n" for p, v in zip(programs, values)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
