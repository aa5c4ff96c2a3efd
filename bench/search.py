"""Beam-search inference throughput: shapes/second at beam 10, and where the time goes.

Usage: ``python -m bench.search csg2d [--checkpoint runs/pretrain/csg2d/best.pt] [--shapes 500] [--beam 10]``

Runs best-of-beam inference (beam search, execution of every candidate,
metric against the target) on real test shapes and reports the share of
time in the network (beam search, including grammar masks) versus the
executor and the metric. Baseline, measured in the same run: the same
search run one shape at a time (no batching across shapes). Last line:
``ratio <batched/one-at-a-time>``.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from plad.domains import get_domain
from plad.model.checkpoint import load_model
from plad.model.decode import beam_search


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain", choices=["csg2d"])
    parser.add_argument("--checkpoint", default="runs/pretrain/csg2d/best.pt")
    parser.add_argument("--shapes", type=int, default=500)
    parser.add_argument("--baseline-shapes", type=int, default=50)
    parser.add_argument("--beam", type=int, default=10)
    parser.add_argument("--batch", type=int, default=100)
    parser.add_argument("--data-dir", default=None)
    args = parser.parse_args(argv)

    domain = get_domain(args.domain)
    if not Path(args.checkpoint).exists():
        raise SystemExit(f"{args.checkpoint}: no such checkpoint (train one with `dvc repro pretrain`)")
    model, _ = load_model(args.checkpoint, expect_domain=args.domain)
    targets = torch.from_numpy(domain.target_data("test", args.data_dir)[: args.shapes])
    beam_search(model, domain.tokens, targets[:4], args.beam)  # warm-up

    t_search = t_exec = t_metric = 0.0
    for start in range(0, len(targets), args.batch):
        batch = targets[start:start + args.batch]
        t0 = time.perf_counter()
        result = beam_search(model, domain.tokens, batch, args.beam)
        t1 = time.perf_counter()
        B, K, L = result.programs.shape
        executed = domain.execute(result.programs.view(B * K, L)).view(B, K, *domain.shape)
        t2 = time.perf_counter()
        values = domain.metric.score_candidates(executed, batch)
        domain.metric.best(values, dim=1)
        t3 = time.perf_counter()
        t_search, t_exec, t_metric = t_search + t1 - t0, t_exec + t2 - t1, t_metric + t3 - t2
    total = t_search + t_exec + t_metric
    ours = len(targets) / total

    base_targets = targets[: args.baseline_shapes]
    t0 = time.perf_counter()
    for i in range(len(base_targets)):
        one = base_targets[i:i + 1]
        result = beam_search(model, domain.tokens, one, args.beam)
        executed = domain.execute(result.programs.view(args.beam, -1)).view(1, args.beam, *domain.shape)
        domain.metric.best(domain.metric.score_candidates(executed, one), dim=1)
    base = len(base_targets) / (time.perf_counter() - t0)

    print(f"{args.domain}: {len(targets)} test shapes, beam {args.beam}, batches of {args.batch}, "
          f"torch threads {torch.get_num_threads()}, model {args.checkpoint}")
    print(f"ours {ours:.1f} shapes/s")
    print(f"share network (beam search) {100 * t_search / total:.1f}%, executor {100 * t_exec / total:.1f}%, "
          f"metric {100 * t_metric / total:.1f}%")
    print(f"baseline (one shape at a time) {base:.1f} shapes/s")
    print(f"ratio {ours / base:.2f}")


if __name__ == "__main__":
    main()
