"""ShapeAssembly domain executor (token programs -> 32^3 grids): the fast path against the original.

Usage: ``python -m bench.shapeassembly_exec [--shapes 10] [--effort default] [--repeats 3] [--search fast,default]``

The original is the frozen copy of the executor and voxelizer before they were made fast
(``tests/reference/shapeassembly_v0.py``). Both run in this process, single-threaded, on the same inputs:

1. the batches of programs that one ``plad.rewrite.driver.search`` at ``--effort`` sends to ``run_batch`` for
   ``--shapes`` test shapes (evenly spaced), replayed through the original ``run_batch`` and the domain's,
   alternately ``--repeats`` times (the prefix cache emptied before each pass of the fast path, so a pass
   costs what it costs inside one search); printed: seconds of each (best pass), the ratio and whether
   grids, unique counts, owners and ok flags are identical;
2. for each effort of ``--search``: the whole search on the same shapes with ``ShapeAssembly.run_batch``
   replaced by the original vs as it is, alternately; seconds, ratio and whether the programs found are
   identical; then the same for the refinement of the shipped network's programs (beam 10, decoded once).

The last line is ``ratio <original/fast>`` of the replayed batches (higher is better).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

from bench.search_speed import network_programs
from plad.domains import get_domain
from plad.domains.shapeassembly import ShapeAssembly
from plad.domains.shapeassembly import cuboids as fast_cuboids


def _original():
    from tests.reference import shapeassembly_v0

    return shapeassembly_v0


def record_batches(domain, targets: torch.Tensor, effort: str) -> list[list[list[int]]]:
    """The program batches (token id lists) one search at ``effort`` executes, in order."""
    from plad.rewrite.driver import search, search_config

    calls: list[list[list[int]]] = []
    own = ShapeAssembly.run_batch

    def recording(self, programs):
        rows = programs.tolist() if isinstance(programs, torch.Tensor) else programs
        calls.append([[int(t) for t in r] for r in rows])
        return own(self, programs)

    ShapeAssembly.run_batch = recording
    try:
        search(domain, targets, search_config(domain, effort=effort))
    finally:
        ShapeAssembly.run_batch = own
    return calls


def same_outputs(a, b) -> bool:
    """Whether two run_batch results (grids, unique, owner, ok) are equal element for element."""
    return all(x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y) for x, y in zip(a, b))


def time_batches(domain, batches, repeats: int) -> tuple[float, float, bool]:
    """Best seconds of the original and of the fast run_batch over ``batches`` (alternating passes), and
    whether every batch's outputs are identical."""
    original = _original()
    best_old = best_new = float("inf")
    identical = True
    for rep in range(repeats):
        start = time.perf_counter()
        old = [original.run_batch(b) for b in batches]
        best_old = min(best_old, time.perf_counter() - start)
        fast_cuboids.clear_cache()
        start = time.perf_counter()
        new = [domain.run_batch(b) for b in batches]
        best_new = min(best_new, time.perf_counter() - start)
        if rep == 0:
            identical = all(same_outputs(a, b) for a, b in zip(old, new))
    return best_old, best_new, identical


def time_search(domain, targets: torch.Tensor, effort: str, repeats: int = 1,
                starts: list[list[int]] | None = None) -> tuple[float, float, bool]:
    """Best seconds of one search with the original run_batch and with the fast one (alternating), and
    whether they find the same programs with the same values; with ``starts``, the refinement of those
    programs (network + refinement) instead of search from scratch."""
    from plad.rewrite.driver import refine, search, search_config

    cfg = search_config(domain, effort=effort)

    def run():
        return search(domain, targets, cfg) if starts is None else refine(domain, starts, targets, cfg.refine)

    original = _original()
    own = ShapeAssembly.run_batch
    best_old = best_new = float("inf")
    identical = True
    for _ in range(repeats):
        ShapeAssembly.run_batch = lambda self, programs: original.run_batch(
            programs.tolist() if isinstance(programs, torch.Tensor) else programs)
        try:
            start = time.perf_counter()
            old = run()
            best_old = min(best_old, time.perf_counter() - start)
        finally:
            ShapeAssembly.run_batch = own
        fast_cuboids.clear_cache()
        start = time.perf_counter()
        new = run()
        best_new = min(best_new, time.perf_counter() - start)
        identical &= old.programs == new.programs and torch.equal(old.values, new.values)
    return best_old, best_new, identical


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=10, help="test shapes, evenly spaced over the split")
    parser.add_argument("--effort", default="default", help="the search whose batches are replayed")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--search", default="fast,default", help="efforts of the whole-search timings ('' none)")
    parser.add_argument("--data-dir", default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    domain = get_domain("shapeassembly")
    try:
        test = domain.target_data("test", args.data_dir)
    except Exception as err:  # noqa: BLE001 - a missing dataset is one line
        sys.exit(f"no ShapeAssembly test shapes: {err}")
    targets = torch.from_numpy(test[np.linspace(0, len(test) - 1, args.shapes).astype(int)])

    batches = record_batches(domain, targets, args.effort)
    n = sum(len(b) for b in batches)
    old, new, identical = time_batches(domain, batches, args.repeats)
    print(f"run_batch on the {len(batches)} batches ({n} programs) of one {args.effort} search on "
          f"{args.shapes} test shapes, torch threads {torch.get_num_threads()}")
    print(f"identical: {identical}")
    starts = network_programs(domain, targets) if args.search else None
    for effort in [e for e in args.search.split(",") if e]:
        s_old, s_new, s_same = time_search(domain, targets, effort)
        print(f"search effort {effort}: original {s_old:.2f} s, fast {s_new:.2f} s, ratio {s_old / s_new:.2f}, "
              f"identical: {s_same}")
        if starts is not None:
            s_old, s_new, s_same = time_search(domain, targets, effort, starts=starts)
            print(f"network + refinement effort {effort}: original {s_old:.2f} s, fast {s_new:.2f} s, "
                  f"ratio {s_old / s_new:.2f}, identical: {s_same}")
    print(f"original {old:.2f} s ({n / old:.0f} programs/s)")
    print(f"fast {new:.2f} s ({n / new:.0f} programs/s)")
    print(f"ratio {old / new:.2f}")
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main())
