"""Executor throughput against a per-program scikit-image renderer.

Usage: ``python -m bench.executor csg2d [--programs N] [--seed S]``

Both run on the same sampled programs in the same process. The baseline is
the straightforward per-program renderer of the test suite
(``tests/reference/csg2d_render.py``: parse the text, draw each primitive with
scikit-image, evaluate the postfix program with numpy). Our time includes
unpacking to bool canvases. The last line is ``ratio <ours/baseline>``.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs


def _best_of(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain", choices=["csg2d"])
    parser.add_argument("--programs", type=int, default=10000)
    parser.add_argument("--baseline-programs", type=int, default=2000,
                        help="the slow baseline runs on the first N programs only")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    from tests.reference.csg2d_render import render

    domain = get_domain(args.domain)
    programs = domain.sample(args.programs, np.random.default_rng(args.seed))
    batch = pad_programs(programs, pad=domain.tokens.index("$"))
    texts = [domain.format(p) for p in programs[: args.baseline_programs]]

    domain.execute(batch[:256])  # warm-up (first call moves tables)
    ours = args.programs / _best_of(lambda: domain.execute(batch), 5)
    base = len(texts) / _best_of(lambda: [render(t) for t in texts], 1)

    same = np.array_equal(domain.execute(batch[: len(texts)]).numpy(), np.stack([render(t) for t in texts]))
    print(f"programs {args.programs} (baseline on {len(texts)}), torch threads {torch.get_num_threads()}")
    print(f"identical outputs {same}")
    print(f"ours {ours:.1f} programs/s")
    print(f"baseline {base:.1f} programs/s")
    print(f"ratio {ours / base:.2f}")


if __name__ == "__main__":
    main()
