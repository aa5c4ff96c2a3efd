"""The grammar samplers' programs per CPU second on one torch thread against torch's default thread count.

Usage: ``python -m bench.sampler [--domains csg2d csg3d shapeassembly] [--programs N] [--repeats R]``

The synthesize stage samples under one torch thread (:func:`plad.device.torch_threads`): each program is
executed on its own to check it, and tiny operations spread over many cores only add synchronization, so the
process spends more CPU seconds for the same programs. On a GPU machine's 16 cores this is the measured cause to
confirm of the samplers' 242 / 278 programs per CPU second there against 2,125 / 973 here (docs/gpu.md). Both
settings sample the same programs (same seed), interleaved ``--repeats`` times in one process; the best of each
is printed, then ``ratio <one thread / default threads>`` in programs per CPU second (above 1: one thread is
cheaper) and whether the programs were identical.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from plad.device import torch_threads
from plad.domains import get_domain


def rate(sample, n: int, threads: int) -> tuple[float, float, list]:
    """(programs per CPU second, per wall second, the programs) of one draw on ``threads`` torch threads."""
    with torch_threads(threads):
        wall, cpu = time.perf_counter(), time.process_time()
        programs = sample(n, np.random.default_rng(0))
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return n / max(cpu, 1e-9), n / max(wall, 1e-9), programs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--domains", nargs="+", default=["csg2d", "csg3d", "shapeassembly"])
    parser.add_argument("--programs", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(),
                        help="the many-thread setting (default: torch's, this machine's cores)")
    args = parser.parse_args(argv)
    print(f"torch threads: 1 against {args.threads}; {args.programs} programs, best of {args.repeats}")
    ratios, identical = [], True
    for name in args.domains:
        domain = get_domain(name)
        for key, sample in domain.samplers().items():
            best = {1: (0.0, 0.0), args.threads: (0.0, 0.0)}
            drawn = {}
            for _ in range(args.repeats):
                for threads in (1, args.threads):
                    cpu_rate, wall_rate, drawn[threads] = rate(sample, args.programs, threads)
                    best[threads] = (max(best[threads][0], cpu_rate), max(best[threads][1], wall_rate))
            same = drawn[1] == drawn[args.threads]
            identical &= same
            ratio = best[1][0] / best[args.threads][0]
            ratios.append(ratio)
            print(f"{name} {key}: 1 thread {best[1][0]:,.0f} programs/CPU s ({best[1][1]:,.0f}/s wall); "
                  f"{args.threads} threads {best[args.threads][0]:,.0f} ({best[args.threads][1]:,.0f}/s wall); "
                  f"ratio {ratio:.2f}; identical {same}")
    print(f"ratio {min(ratios):.2f} (smallest); identical {identical}")
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
