"""csg3d executor throughput against the per-program numpy reference.

Usage: ``python -m bench.csg3d [--programs N] [--baseline-programs M] [--sampler K] [--seed S]``

Both run on the same sampled programs (2..12 primitives, as for pretraining)
in the same process, single-threaded. The baseline is the straightforward
per-program renderer of the test suite (``tests/reference/csg3d_render.py``:
read the text, evaluate each primitive's inside test on all 32^3 voxel
centers in float64, combine recursively). Our time includes unpacking to
bool grids; on the CPU it runs the compiled kernels (``plad.domains.csg3d.compiled``) where numba is
installed, and ``--numpy`` times the path before them (programs one at a time in numpy) instead. With
``--sampler K`` the synthetic sampler's throughput (sampling,
execution and rejection of degenerate programs) is measured on K programs too.
The last line is ``ratio <ours/baseline>``.
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
    parser.add_argument("--programs", type=int, default=10000)
    parser.add_argument("--baseline-programs", type=int, default=1000,
                        help="the slow baseline runs on the first N programs only")
    parser.add_argument("--sampler", type=int, default=0, help="also time sampling this many programs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--numpy", action="store_true", help="time the numpy per-program path, not the compiled one")
    args = parser.parse_args(argv)
    from plad import jit

    jit.load()   # the compiled kernels from the first call, as a long process runs them once it has earned them
    torch.set_num_threads(1)
    if args.numpy:
        import importlib

        importlib.import_module("plad.domains.csg3d.executor")._COMPILED = False

    from tests.reference.csg3d_render import render

    domain = get_domain("csg3d")
    if args.sampler:
        start = time.perf_counter()
        domain.sample(args.sampler, np.random.default_rng(args.seed + 1))
        seconds = time.perf_counter() - start
        print(f"sampler {args.sampler} programs in {seconds:.1f} s: {args.sampler / seconds:.1f} programs/s")
    programs = domain.sample(args.programs, np.random.default_rng(args.seed))
    batch = pad_programs(programs)
    texts = [domain.format(p) for p in programs[: args.baseline_programs]]

    domain.execute(batch[:256])  # warm-up (first call builds the lookup tables)
    ours = args.programs / _best_of(lambda: domain.execute(batch), 3)
    base = len(texts) / _best_of(lambda: [render(t) for t in texts], 1)

    same = np.array_equal(domain.execute(batch[: len(texts)]).numpy(), np.stack([render(t) for t in texts]))
    print(f"programs {args.programs} (baseline on {len(texts)}), mean length "
          f"{np.mean([len(p) for p in programs]):.1f} tokens, torch threads {torch.get_num_threads()}")
    print(f"identical outputs {same}")
    print(f"ours {ours:.1f} programs/s")
    print(f"baseline {base:.1f} programs/s")
    print(f"ratio {ours / base:.2f}")


if __name__ == "__main__":
    main()
