"""Search and rewriter throughput, and where the time goes, against unscreened search.

Usage: ``python -m bench.rewrite DOMAIN [--shapes N] [--baseline-shapes M] [--prepared data/prepared]``

Search from scratch (the domain's default configuration, one torch thread)
on the first N prepared test shapes: shapes/s, candidates/s (screened, and
executed and scored exactly), and the share of time in execution (the
screen's and the exact executor's) versus scoring (the screen's cheap score
and the domain metric). Then ``refine`` (one round: PO sweeps, pruning, one
insertion) of the programs found: shapes/s and candidates/s. Baseline,
measured in the same run on the first M shapes: the same search with the
domain's screen switched off, so every candidate is executed by the
domain's executor and scored by its metric (as straightforward code does),
against the screened search on the same M shapes (mean metric of both).
Last line: ``ratio <screened/unscreened shapes per second>`` (1 for a domain
without a screen).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from plad.data.files import load_prepared
from plad.domains import get_domain
from plad.rewrite import refine, search, search_config


def _report(label: str, n: int, result) -> float:
    s = result.stats
    execution = s.screen_exec + s.exec
    scoring = s.screen_score + s.metric
    other = max(result.seconds - execution - scoring, 0.0)
    print(f"{label}: {n} shapes in {result.seconds:.1f} s = {n / result.seconds:.2f} shapes/s; "
          f"mean {result.values.mean().item():.4f}")
    print(f"  candidates: {s.screened} screened ({s.screened / result.seconds:.0f}/s), "
          f"{s.scored} scored exactly ({s.scored / result.seconds:.0f}/s)")
    print(f"  time: execution {execution / result.seconds:.0%} (screen {s.screen_exec:.1f} s, exact {s.exec:.1f} s), "
          f"scoring {scoring / result.seconds:.0%} (screen {s.screen_score:.1f} s, metric {s.metric:.1f} s), "
          f"other {other / result.seconds:.0%}; accepted {s.counts}")
    return n / result.seconds


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain")
    parser.add_argument("--shapes", type=int, default=100)
    parser.add_argument("--baseline-shapes", type=int, default=10)
    parser.add_argument("--prepared", default="data/prepared")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    domain = get_domain(args.domain)
    path = Path(args.prepared) / f"{args.domain}.npz"
    if not path.is_file():
        raise SystemExit(f"{path}: no such prepared dataset (run the prepare stages first)")
    targets = torch.from_numpy(load_prepared(path, "test")[: args.shapes])
    config = search_config(domain)
    search(domain, targets[:2], config)                                   # warm-up (lookup tables)

    found = search(domain, targets, config)
    _report("search", len(targets), found)
    refined = refine(domain, found.programs, targets,
                     search_config(domain, **{"refine.rounds": 1}).refine)
    _report("refine (1 round, from the search's programs)", len(targets), refined)

    m = args.baseline_shapes
    if domain.rewrite.screen_keep is None:
        print(f"the {args.domain} domain has no screen: every candidate is scored exactly already")
    screened = search(domain, targets[:m], config)
    unscreened = search(domain, targets[:m], search_config(domain, **{"refine.screen": False}))
    ours = _report(f"screened search, first {m} shapes", m, screened)
    base = _report(f"baseline: search without the screen, first {m} shapes", m, unscreened)
    print(f"ratio {ours / base:.2f}")


if __name__ == "__main__":
    main()
