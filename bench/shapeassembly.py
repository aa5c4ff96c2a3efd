"""ShapeAssembly executor throughput (full hierarchical language, text -> world cuboids).

Usage: ``python -m bench.shapeassembly [--programs N] [--tar PATH] [--repeats R]``

Programs: the 120 fixture programs of ``../shared/fixtures/shapeassembly_reference.npz``
(default), or the first N programs of a ``partnet_programs.tar.gz`` (``--tar``).
Both executors parse and execute every program to world-space cuboids in
the same process, single-threaded. The baseline is the straightforward
per-program algorithm of the original: the same statements, but the grow
step's closest pair found by exhaustive search over all 1000 x 1000 sample
pairs (``nearest_pair_brute``; the original uses faiss for the same search).
For scale, the original's own time on the fixture (median of its recorded
``exec_seconds``) is printed too. The last line is ``ratio <ours/baseline>``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from plad.data.datasets.partnet.execute import nearest_pair_brute, run_text

FIXTURE = Path(__file__).resolve().parent.parent.parent / "shared" / "fixtures" / "shapeassembly_reference.npz"


def _best_of(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--programs", type=int, default=None, help="use the first N programs")
    parser.add_argument("--tar", default=None, help="partnet_programs.tar.gz instead of the fixture")
    parser.add_argument("--fixture", default=str(FIXTURE))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    original = None
    if args.tar:
        from plad.data.datasets.partnet.dataset import read_source

        programs, _ = read_source(args.tar)
        texts = [programs[k] for k in sorted(programs)]
    else:
        if not Path(args.fixture).is_file():
            sys.exit(f"{args.fixture} is missing; pass --fixture or --tar")
        z = np.load(args.fixture)
        texts = [str(t) for t in z["program_text"]]
        original = float(np.median(z["exec_seconds"]))
    texts = texts[: args.programs] if args.programs else texts

    ours_out = [run_text(t) for t in texts]                       # warm-up and outputs
    base_out = [run_text(t, nearest=nearest_pair_brute) for t in texts]
    diff = max(float(np.abs(a - b).max()) if len(a) else 0.0 for a, b in zip(ours_out, base_out))
    same_count = all(len(a) == len(b) for a, b in zip(ours_out, base_out))
    ours = len(texts) / _best_of(lambda: [run_text(t) for t in texts], args.repeats)
    base = len(texts) / _best_of(lambda: [run_text(t, nearest=nearest_pair_brute) for t in texts], 1)
    print(f"programs {len(texts)}, torch threads {torch.get_num_threads()}")
    print(f"same cuboid counts {same_count}, max |ours - baseline| {diff:.2e}")
    if original is not None:
        print(f"original (recorded in the fixture, median) {1 / original:.1f} programs/s")
    print(f"ours {ours:.1f} programs/s")
    print(f"baseline {base:.1f} programs/s")
    print(f"ratio {ours / base:.2f}")


if __name__ == "__main__":
    main()
