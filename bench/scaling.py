"""Scaling on this machine: DDP training steps/s with 1 and 2 CPU processes, round inference with 1 and 2 Dask workers.

Usage: ``python -m bench.scaling [--params params.yaml] [--profile PROFILE] [--domain csg2d] [--root .]
[--checkpoint FILE] [--steps 30] [--shapes 400] [--shards 4]``

The configs are those of the pipeline: ``--params`` with its profile, or
``profiles/<PROFILE>.yaml`` applied instead (:func:`plad.config.load_params`);
the synthetic programs and the prepared shapes are those of the layout root
``--root`` (:mod:`plad.layout`: ``data/synthetic/<domain>.npz``,
``data/prepared/<domain>.npz``).

Training: the pretraining step of ``pretrain.<domain>`` (its
architecture and batch size per process; batches dealt out from one
permutation as in :mod:`plad.stages.pretrain`, the loss through
:func:`plad.learn.distributed.data_parallel`), timed over ``--steps`` optimizer
steps after warm-up, in 1 process and in 2 processes (gloo on loopback, one
torch thread each). Throughput is shapes per second over all processes.

Inference: the round's sharded beam inference over ``--shapes`` real
training shapes (``finetune.<domain>``'s ``plad`` beam and batch), the shards
(:func:`flows.finetune._infer_shard`, as the flow's tasks run them) mapped
over a Dask ``LocalCluster`` of 1 and of 2 worker processes with one thread
each, after one warm-up shard per worker. Without ``--checkpoint`` the model
has the params' architecture and seeded random weights (the time depends on
the architecture and on the programs' lengths, so a trained model's time
differs).

The baselines are the 1-process runs of the same invocation; the last lines
are ``ratio training <2 procs / 1 proc>`` and ``ratio inference <2 workers / 1 worker>``
(throughput ratios; 2.0 would be perfect scaling on 2 cores). Each line also
gives the CPU seconds the processes spent per step (per shape), and the
machine's load average is printed before and after: on a machine shared with
other work, wall-clock scaling says more about the other work than about DDP
or Dask, while CPU time per unit of work shows the overhead of the extra
processes.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

WARMUP_STEPS = 3


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pretrain_config(args: argparse.Namespace):
    """The ``pretrain.<domain>`` config of the params (with the profile)."""
    from plad.config import load_params, section
    from plad.learn.pretrain import PretrainConfig

    return section(load_params(args.params, profile=args.profile), f"pretrain.{args.domain}", PretrainConfig)


def _train_rank(rank: int, world: int, port: int, args: argparse.Namespace, results) -> None:
    """One process of the training measurement (``world`` of them): steps/s of the pretraining step."""
    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(world), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    from plad.domains import get_domain
    from plad.layout import Layout
    from plad.learn import distributed as dist
    from plad.learn.synthetic import load_programs, make_batch
    from plad.model.network import ModelConfig, PLADNet

    cfg = pretrain_config(args)
    domain = get_domain(args.domain)
    train = load_programs(Layout(args.root).synthetic(args.domain))["train"]
    torch.manual_seed(0)
    model = PLADNet(ModelConfig.for_domain(cfg.model, domain))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)
    step_loss = dist.data_parallel(model, lambda m, b: m.loss(*b))
    bs = cfg.train.batch_size
    perm = torch.randperm(len(train), generator=torch.Generator().manual_seed(0))
    starts = iter(dist.chunk_starts(len(perm), bs))
    model.train()
    times = []
    for step in range(WARMUP_STEPS + args.steps):
        if step == WARMUP_STEPS:
            dist.barrier()
            cpu0 = time.process_time()
        t0 = time.perf_counter()
        start = next(starts)
        loss, _ = step_loss(make_batch(domain, train[perm[start:start + bs]], torch.device("cpu")))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.train.grad_clip)
        opt.step()
        times.append(time.perf_counter() - t0)
    cpu = time.process_time() - cpu0
    dist.barrier()
    results.put((rank, sum(times[WARMUP_STEPS:]), cpu))
    if world > 1:
        torch.distributed.destroy_process_group()


def train_throughput(world: int, args: argparse.Namespace) -> tuple[float, float, float]:
    """(optimizer steps/s, shapes/s over all processes, CPU seconds per step per process) with ``world``
    processes."""
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    results = ctx.SimpleQueue()
    port = _free_port()
    if world == 1:   # the single-process path: no process group, no DDP
        _train_rank(0, 1, port, args, results)
    else:
        mp.start_processes(_train_rank, args=(world, port, args, results), nprocs=world, start_method="spawn")
    measured = sorted(results.get() for _ in range(world))
    seconds = measured[0][1]   # rank 0's wall time
    cpu = sum(m[2] for m in measured) / world / args.steps
    for key in ("RANK", "LOCAL_RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT"):
        os.environ.pop(key, None)   # the 1-process call set them in this process
    bs = pretrain_config(args).train.batch_size
    return args.steps / seconds, args.steps * bs * world / seconds, cpu


def infer_throughput(workers: int, model, shapes: np.ndarray, beam: int, batch: int, args) -> tuple[float, float]:
    """(shapes/s, CPU milliseconds per shape summed over the workers) of the sharded round inference on a
    LocalCluster of ``workers`` processes."""
    from distributed import Client, LocalCluster

    from flows.finetune import _infer_shard

    env = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                      env=env) as cluster, Client(cluster) as client:
        remote_model = client.scatter(model, broadcast=True)
        warm = [client.submit(_infer_shard, remote_model, args.domain, shapes[:2], beam, batch, 1, pure=False,
                              workers=[w]) for w in client.scheduler_info()["workers"]]
        client.gather(warm)
        parts = np.array_split(np.arange(len(shapes)), args.shards)
        cpu0 = sum(client.run(time.process_time).values())
        t0 = time.perf_counter()
        futures = [client.submit(_infer_shard, remote_model, args.domain, shapes[p], beam, batch, 1, pure=False)
                   for p in parts]
        client.gather(futures)
        seconds = time.perf_counter() - t0
        cpu = sum(client.run(time.process_time).values()) - cpu0
        return len(shapes) / seconds, 1000 * cpu / len(shapes)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--profile", help="apply profiles/<PROFILE>.yaml instead of the one the params name")
    parser.add_argument("--domain", default="csg2d")
    parser.add_argument("--root", default=".", help="layout root of the synthetic and prepared data (plad.layout)")
    parser.add_argument("--checkpoint", default=None, help="model for inference (default: random weights)")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--shapes", type=int, default=400)
    parser.add_argument("--shards", type=int, default=4)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    from plad.config import load_params, section
    from plad.data.files import load_prepared
    from plad.domains import get_domain
    from plad.layout import Layout
    from plad.model.checkpoint import load_model
    from plad.model.network import ModelConfig, PLADNet
    from plad.stages.finetune import FinetuneStageConfig

    pre = pretrain_config(args)
    ft = section(load_params(args.params, profile=args.profile), f"finetune.{args.domain}", FinetuneStageConfig)
    domain = get_domain(args.domain)
    if args.checkpoint:
        model, _ = load_model(args.checkpoint, expect_domain=args.domain)
    else:
        torch.manual_seed(0)
        model = PLADNet(ModelConfig.for_domain(pre.model, domain)).eval()
    shapes = load_prepared(Layout(args.root).prepared(args.domain), "train")[: args.shapes]

    params = args.params + (f" with profile {args.profile}" if args.profile else "")
    print(f"{args.domain}, {params}: machine with {os.cpu_count()} cores, 1 torch thread per process; "
          f"load average before {os.getloadavg()[0]:.2f}")
    steps1, shapes1, cpu1 = train_throughput(1, args)
    steps2, shapes2, cpu2 = train_throughput(2, args)
    print(f"training (pretraining step, batch {pre.train.batch_size} per process, {args.steps} steps): "
          f"1 process {steps1:.2f} steps/s {shapes1:.1f} shapes/s ({cpu1:.3f} CPU s/step); "
          f"2 processes (DDP, gloo) {steps2:.2f} steps/s {shapes2:.1f} shapes/s ({cpu2:.3f} CPU s/step per process)")
    beam, batch = ft.plad.infer_beam, ft.plad.infer_batch
    inf1, icpu1 = infer_throughput(1, model, shapes, beam, batch, args)
    inf2, icpu2 = infer_throughput(2, model, shapes, beam, batch, args)
    print(f"inference ({len(shapes)} training shapes, beam {beam}, {args.shards} shards, "
          f"{'checkpoint ' + args.checkpoint if args.checkpoint else 'random weights'}): "
          f"1 Dask worker {inf1:.1f} shapes/s ({icpu1:.1f} CPU ms/shape); "
          f"2 Dask workers {inf2:.1f} shapes/s ({icpu2:.1f} CPU ms/shape)")
    print(f"load average after {os.getloadavg()[0]:.2f}")
    print(f"ratio training {shapes2 / shapes1:.2f}")
    print(f"ratio inference {inf2 / inf1:.2f}")


if __name__ == "__main__":
    main()
