"""Beam-search decoding time: preallocated key/value caches (greedy: no row reordering) against the
previous decoding, which concatenated every layer's cache at each step and reordered its rows (an
identity at beam 1). Same weights, same shapes, the same programs.

Usage: ``python -m bench.decode [csg3d] [--model CKPT] [--params params.yaml] [--batch 50] [--beams 1,5]
[--repeats 5] [--threads 1]``

The network is a checkpoint (``--model``) or, without one, the domain's pretraining config at
initialization (its programs run to the length cap, the worst case); the shapes are real prepared
test shapes when ``data/prepared/<domain>.npz`` exists, else random occupancy. The encoder is run
once outside the timings (``bench.encoder`` times it). The two ways take turns so that a shared
machine's load falls on both alike; prints the best milliseconds per shape of each per beam, and last
``ratio <previous / ours>`` of the first beam (ours / baseline in speed, as in the other benchmarks).
"""
from __future__ import annotations

import argparse
import time
from contextlib import contextmanager

import torch

import plad.model.network
from bench import prepared_test_shapes
from plad.config import load_params, section
from plad.domains import get_domain
from plad.learn.pretrain import PretrainConfig
from plad.model.decode import beam_search
from plad.model.network import KVCache, ModelConfig, PLADNet


class ConcatCache:
    """The previous cache: the past's keys and values concatenated again at every step."""

    def __init__(self, k: torch.Tensor, v: torch.Tensor, capacity: int):
        self.k, self.v = k, v

    def append(self, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        self.k, self.v = torch.cat([self.k, k], 2), torch.cat([self.v, v], 2)
        return self.k, self.v

    def select(self, index: torch.Tensor) -> ConcatCache:
        return ConcatCache(self.k.index_select(0, index), self.v.index_select(0, index), 0)


@contextmanager
def previous_decoding(model: PLADNet):
    """Concatenated caches, and every step's rows reordered (beam search did so even at beam 1)."""
    step = model.step

    def reordering_step(tokens, caches, position):
        rows = torch.arange(len(tokens), device=tokens.device)
        return step(tokens, [c.select(rows) for c in caches], position)

    plad.model.network.KVCache = ConcatCache
    model.step = reordering_step
    try:
        yield
    finally:
        plad.model.network.KVCache = KVCache
        del model.step


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain", nargs="?", default="csg3d")
    parser.add_argument("--model", help="checkpoint (default: the pretraining config at initialization)")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--beams", default="1,5")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    domain = get_domain(args.domain)
    torch.manual_seed(0)
    if args.model:
        from plad.model.checkpoint import load_model

        model, _ = load_model(args.model, expect_domain=args.domain)
        net = args.model
    else:
        cfg = section(load_params(args.params), f"pretrain.{args.domain}", PretrainConfig)
        model = PLADNet(ModelConfig.for_domain(cfg.model, domain))
        net = "untrained pretraining config"
    model.eval()
    x, source = prepared_test_shapes(domain, args.batch)
    beams = [int(b) for b in args.beams.split(",")]
    print(f"{args.domain} decoding, {net}; {source}; {args.threads} thread(s)")
    with torch.no_grad():
        prefix = model.encode(x)

        def run(way: str, beam: int):
            if way == "ours":
                return beam_search(model, domain.tokens, x, beam, prefix=prefix)
            with previous_decoding(model):
                return beam_search(model, domain.tokens, x, beam, prefix=prefix)

        ratios = []
        for beam in beams:
            best = {"ours": float("inf"), "previous": float("inf")}
            results = {}
            for r in range(args.repeats):
                for way in (("ours", "previous") if r % 2 == 0 else ("previous", "ours")):
                    start = time.perf_counter()
                    results[way] = run(way, beam)
                    best[way] = min(best[way], time.perf_counter() - start)
            same = (torch.equal(results["ours"].programs, results["previous"].programs)
                    and torch.equal(results["ours"].logp, results["previous"].logp))
            o, p = best["ours"], best["previous"]
            mean_len = float(results["ours"].lengths.float().mean())
            print(f"beam {beam:2d}: previous {1e3 * p / len(x):.2f} ms/shape, ours {1e3 * o / len(x):.2f} ms/shape, "
                  f"x{p / o:.2f}; mean length {mean_len:.1f}; same programs and scores: {same}")
            ratios.append(p / o)
    print(f"ratio {ratios[0]:.2f}")


if __name__ == "__main__":
    main()
