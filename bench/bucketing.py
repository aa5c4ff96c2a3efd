"""Training-step time with length-bucketed batches against plain random batches, on the same examples.

Usage: ``python -m bench.bucketing [csg3d] [--params params.yaml] [--pools 3] [--pool 8] [--threads 1]``

The network and batch size are the domain's pretraining config (params file with its profile);
the examples are freshly sampled synthetic programs in canonical form, executed once beforehand
(the executor's time is the same for every scheme). Every pool of ``pool`` batches' worth of
examples is trained on (forward and backward of the loss, no optimizer step) three ways, taking
turns batch by batch:

* ``padded``: plain batches, every row as long as the length cap (what pretraining did before);
* ``trimmed``: the same batches cut to their longest program;
* ``bucketed``: the pool sorted by length and cut into batches (:mod:`plad.data.batching`).

Prints each scheme's seconds and padding share, the mean per-token loss of the three (equal:
the loss does not depend on the batching), the time ratios, and last ``ratio <padded / bucketed>``,
the speed-up of a training step (as in the other benchmarks: ours / baseline in steps per second).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from plad.config import load_params, section
from plad.data.batching import bucket_batches, padding_share
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.pretrain import PretrainConfig
from plad.model.network import ModelConfig, PLADNet


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain", nargs="?", default="csg3d")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--pools", type=int, default=3, help="pools of examples timed")
    parser.add_argument("--pool", type=int, default=8, help="batches per pool (the bucket_pool setting)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = section(load_params(args.params), f"pretrain.{args.domain}", PretrainConfig)
    domain = get_domain(args.domain)
    bs, n_pool = cfg.train.batch_size, args.pool * cfg.train.batch_size
    rng = np.random.default_rng(args.seed)
    programs = [domain.canonical(p) for p in domain.sample(args.pools * n_pool, rng)]
    full = pad_programs(programs)
    full = torch.cat([full, torch.zeros(len(full), domain.tokens.max_len - full.shape[1], dtype=torch.long)], 1)
    lengths = torch.tensor([len(p) for p in programs])
    shapes = domain.execute(full)
    torch.manual_seed(args.seed)
    model = PLADNet(ModelConfig.for_domain(cfg.model, domain))
    model.eval()   # no dropout: the three schemes compute the same loss

    def schemes(idx: np.ndarray) -> dict[str, list[tuple[np.ndarray, int | None]]]:
        plain = [idx[i:i + bs] for i in range(0, len(idx), bs)]
        buckets = [idx[b] for b in bucket_batches(lengths[idx].numpy(), bs, rng)]
        return {"padded": [(b, None) for b in plain], "trimmed": [(b, 0) for b in plain],
                "bucketed": [(b, 0) for b in buckets]}

    seconds = {k: 0.0 for k in ("padded", "trimmed", "bucketed")}
    nll = {k: 0.0 for k in seconds}
    batch_lengths: dict[str, list[np.ndarray]] = {k: [] for k in seconds}
    tokens = 0
    for p in range(args.pools):
        idx = np.arange(p * n_pool, (p + 1) * n_pool)
        plan = schemes(idx)
        # the schemes take turns batch by batch (in a rotating order), so that the load of the shared
        # machine falls on all of them alike
        turns = [(name, j) for j in range(args.pool) for name in np.roll(list(plan), -j)]
        for name, j in turns:
            b, cut = plan[name][j]
            i = torch.from_numpy(b)
            width = domain.tokens.max_len if cut is None else int(lengths[i].max())
            start = time.perf_counter()
            loss, _ = model.loss(shapes[i], full[i, :width], lengths[i])
            loss.backward()
            seconds[name] += time.perf_counter() - start
            model.zero_grad(set_to_none=True)
            nll[name] += float(loss.detach()) * int(lengths[i].sum())
            batch_lengths[name].append(lengths[i].numpy())
        tokens += int(lengths[idx].sum())
    for name in seconds:
        share = padding_share(batch_lengths[name], domain.tokens.max_len if name == "padded" else None)
        print(f"{name:9s} {seconds[name]:8.2f} s  padding {share:6.1%}  loss/token {nll[name] / tokens:.6f}")
    print(f"time trimmed/padded {seconds['trimmed'] / seconds['padded']:.3f}")
    print(f"time bucketed/trimmed {seconds['bucketed'] / seconds['trimmed']:.3f}")
    print(f"time bucketed/padded {seconds['bucketed'] / seconds['padded']:.3f}")
    print(f"ratio {seconds['padded'] / seconds['bucketed']:.3f}")   # speed-up, as the other benchmarks


if __name__ == "__main__":
    main()
