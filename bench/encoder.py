"""The CNN encoder's time: its forward (pool before ReLU, the coordinates' convolution once per batch,
a channels-last first block in 3D) against the plain definition, same weights, same shapes.

Usage: ``python -m bench.encoder [csg3d] [--params params.yaml] [--batch 32] [--repeats 10] [--threads 1]``

The network is the domain's pretraining config (params file with its profile); the shapes are real
prepared test shapes when ``data/prepared/<domain>.npz`` exists, else random occupancy. Times the
encoding (evaluation mode, no gradient) and a training step's share (forward and backward of a
loss on the visual tokens), the two ways taking turns so that a shared machine's load falls on both
alike; prints the best seconds per shape of each, the largest difference of the outputs, and last
``ratio <plain / fast>`` of the evaluation (as in the other benchmarks: ours / baseline in speed).
"""
from __future__ import annotations

import argparse
import time

import torch

from bench import prepared_test_shapes
from plad.config import load_params, section
from plad.domains import get_domain
from plad.learn.pretrain import PretrainConfig
from plad.model.network import ModelConfig, PLADNet


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain", nargs="?", default="csg3d")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = section(load_params(args.params), f"pretrain.{args.domain}", PretrainConfig)
    domain = get_domain(args.domain)
    torch.manual_seed(0)
    enc = PLADNet(ModelConfig.for_domain(cfg.model, domain)).encoder
    x, source = prepared_test_shapes(domain, args.batch)
    print(f"{args.domain} encoder {cfg.model.enc_channels}, kernel {cfg.model.enc_kernel}, "
          f"coordinates {cfg.model.coord_channels}; {source}; {args.threads} thread(s)")

    def step(forward):
        enc.zero_grad()
        forward(x).square().mean().backward()

    ways = {"fast": enc.forward, "plain": enc.forward_plain}
    best = {(w, k): float("inf") for w in ways for k in ("eval", "train")}
    for r in range(args.repeats):
        for name in (list(ways) if r % 2 == 0 else list(ways)[::-1]):
            enc.eval()
            with torch.no_grad():
                start = time.perf_counter()
                ways[name](x)
                best[name, "eval"] = min(best[name, "eval"], time.perf_counter() - start)
            enc.train()
            start = time.perf_counter()
            step(ways[name])
            best[name, "train"] = min(best[name, "train"], time.perf_counter() - start)
    enc.eval()
    with torch.no_grad():
        diff = float((enc(x) - enc.forward_plain(x)).abs().max())
    for kind in ("eval", "train"):
        f, p = best["fast", kind], best["plain", kind]
        print(f"{kind:5s}: plain {1e3 * p / len(x):.2f} ms/shape, fast {1e3 * f / len(x):.2f} ms/shape, x{p / f:.2f}")
    print(f"largest output difference {diff:.1e}")
    print(f"ratio {best['plain', 'eval'] / best['fast', 'eval']:.2f}")


if __name__ == "__main__":
    main()
