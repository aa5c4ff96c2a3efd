"""Search-only numbers ("search, no network") on a domain's real shapes.

Usage::

    python -m plad.tools.search_baseline DOMAIN [--split test] [--limit N | --spaced N] [--workers W]
        [--prepared data/prepared] [--set KEY=VALUE ...] [--out FILE.json]

Runs :func:`plad.rewrite.baseline.run_baseline`: :func:`plad.rewrite.search` (the domain's default search
configuration, with ``--set`` overrides, e.g. ``--set effort=best``) on the prepared shapes of a split (all,
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
import os
import sys
from pathlib import Path

from plad.rewrite.baseline import run_baseline


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
