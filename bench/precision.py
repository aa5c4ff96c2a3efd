"""Training steps in bf16 autocast against float32 on this machine's CPU: the same weights, the same batches.

Usage: ``python -m bench.precision [csg3d] [--params params.yaml] [--profile PROFILE] [--batch 32] [--steps 8]
[--threads 1]``

The network is ``pretrain.<domain>``'s of the params file with its profile (or ``--profile``); the batches
are programs of the domain's sampler executed as pretraining executes them (:func:`plad.learn.synthetic.make_batch`).
Two copies of the network with the same weights each take ``--steps`` pretraining steps
(:func:`plad.learn.train.train_step`, Adam, gradient clip) on the same batches, one in float32 and one under
bf16 autocast (params ``precision: bf16``), taking turns step by step so that a shared machine's load falls on
both alike. Prints the median milliseconds per step (wall clock and this process's CPU time) and shapes per
second of each, the first step's loss in both and its relative change, and last ``ratio <fp32 time / bf16
time>`` of the CPU times (bf16's speed-up; as in the other benchmarks, ours over the baseline's speed): on a
machine shared with other work the CPU time of a step is what it costs, its wall clock what the others left.
CPUs with AVX512-BF16 or AMX run bf16 matrix products natively; elsewhere bf16 may well be slower.
"""
from __future__ import annotations

import argparse
import copy
import os
import statistics
import time

import numpy as np
import torch


def main(argv: list[str] | None = None) -> None:
    from plad.config import load_params, section
    from plad.device import resolve_precision
    from plad.domains import get_domain
    from plad.learn.pretrain import PretrainConfig
    from plad.learn.synthetic import make_batch
    from plad.learn.train import train_step
    from plad.model.network import ModelConfig, PLADNet, count_parameters

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain", nargs="?", default="csg3d")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--profile", default=None, help="apply profiles/<PROFILE>.yaml instead of the one the "
                                                         "params name")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cpu = torch.device("cpu")
    cfg = section(load_params(args.params, profile=args.profile), f"pretrain.{args.domain}", PretrainConfig)
    domain = get_domain(args.domain)
    rng = np.random.default_rng(0)
    batches = []
    for _ in range(args.steps):
        rows = torch.full((args.batch, domain.tokens.max_len), -1, dtype=torch.long)
        for i, p in enumerate(domain.sample(args.batch, rng)):
            rows[i, :len(p)] = torch.tensor(p)
        batches.append(make_batch(domain, rows, cpu))
    torch.manual_seed(0)
    nets = {"fp32": PLADNet(ModelConfig.for_domain(cfg.model, domain))}
    nets["bf16"] = copy.deepcopy(nets["fp32"])
    opts = {k: torch.optim.Adam(m.parameters(), lr=cfg.train.lr) for k, m in nets.items()}
    precision = {k: resolve_precision(k, cpu) for k in nets}
    length = np.mean([float(b[2].float().mean()) for b in batches])
    print(f"{args.domain}: {count_parameters(nets['fp32']):,} parameters ({cfg.model.d_model} wide, "
          f"{cfg.model.n_layers} layers, encoder {list(cfg.model.enc_channels)}), batch {args.batch}, programs of "
          f"{length:.0f} tokens on average, {args.threads} thread(s); CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}, oneDNN bf16 "
          f"{'yes' if torch.ops.mkldnn._is_mkldnn_bf16_supported() else 'no'}")
    times: dict[str, list[float]] = {k: [] for k in nets}
    cpu: dict[str, list[float]] = {k: [] for k in nets}
    first: dict[str, float] = {}
    for step, batch in enumerate(batches):
        for name in (list(nets) if step % 2 == 0 else list(nets)[::-1]):
            torch.manual_seed(step)   # the same dropout draws for both, as far as the arithmetic allows
            model = nets[name].train()
            start, start_cpu = time.perf_counter(), time.process_time()
            loss, _ = train_step(model, opts[name], lambda b, m=model: m.loss(*b), batch, cfg.train.grad_clip,
                                 precision[name])
            times[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
            first.setdefault(name, float(loss))
    # the first step of each pays one-time costs (oneDNN's kernel choice); the median of the rest
    med = {k: statistics.median(v[1:] if len(v) > 2 else v) for k, v in times.items()}
    med_cpu = {k: statistics.median(v[1:] if len(v) > 2 else v) for k, v in cpu.items()}
    for name in nets:
        print(f"{name}: {1e3 * med[name]:.0f} ms per step wall, {1e3 * med_cpu[name]:.0f} ms CPU; "
              f"{args.batch / med_cpu[name]:.1f} shapes per CPU second (median of {max(len(times[name]) - 1, 1)} "
              f"steps; first step's loss {first[name]:.5f})")
    change = abs(first["bf16"] - first["fp32"]) / first["fp32"]
    print(f"first step's loss, bf16 against fp32: relative change {change:.1e}")
    print(f"wall-clock ratio {med['fp32'] / med['bf16']:.2f} (load average {os.getloadavg()[0]:.1f})")
    print(f"ratio {med_cpu['fp32'] / med_cpu['bf16']:.2f}")


if __name__ == "__main__":
    main()
