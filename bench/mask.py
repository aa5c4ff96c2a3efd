"""Grammar mask time: each stack top's effect looked up in a table (TokenTable._table) against comparing
every rule of every token with the stack at each step (the previous way, ``lookup_limit=0``).

Usage: ``python -m bench.mask [shapeassembly] [--rows 500] [--repeats 5] [--threads 1]``

Random masked rollouts of ``--rows`` programs (500: a batch of 50 shapes at beam 10), mask and advance at
every step until all are complete; the two ways take turns and must give the same masks. Prints the best
milliseconds per rollout batch of each, and last ``ratio <previous / ours>``.
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import torch

from plad.domains import get_domain


def rollout(table, rows: int, seed: int) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    state, masks = table.initial_state(rows), []
    while not bool(state.done.all()):
        mask = table.mask(state)
        masks.append(mask)
        tok = torch.multinomial(mask.float() + state.done.float()[:, None], 1, generator=gen)[:, 0]
        state = table.advance(state, tok)
    return masks


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain", nargs="?", default="shapeassembly")
    parser.add_argument("--rows", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    ours = get_domain(args.domain).tokens
    previous = dataclasses.replace(ours, lookup_limit=0)
    best = {"ours": float("inf"), "previous": float("inf")}
    masks = {}
    for r in range(args.repeats):
        for way, table in (((("ours", ours), ("previous", previous))) if r % 2 == 0
                           else (("previous", previous), ("ours", ours))):
            start = time.perf_counter()
            masks[way] = rollout(table, args.rows, seed=r)
            best[way] = min(best[way], time.perf_counter() - start)
        same = len(masks["ours"]) == len(masks["previous"]) and all(
            torch.equal(a, b) for a, b in zip(masks["ours"], masks["previous"]))
        if not same:
            raise SystemExit("the two ways gave different masks")
    steps = len(masks["ours"])
    print(f"{args.domain}: {args.rows} random masked rollouts, {steps} steps (last repeat), {args.threads} thread(s); "
          f"{len(ours)} tokens, {len(ours.symbols)} symbols")
    print(f"previous (compare every rule): {1e3 * best['previous']:.1f} ms; ours (table per stack top): "
          f"{1e3 * best['ours']:.1f} ms; same masks: True")
    print(f"ratio {best['previous'] / best['ours']:.2f}")


if __name__ == "__main__":
    main()
