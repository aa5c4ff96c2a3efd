"""Is the paper profile ready for a GPU? A few steps of every part of the pipeline, for every domain, at the
paper profile's model and batch sizes: throughput and peak memory per part, and on CUDA agreement with the CPU.

Usage: ``python -m bench.gpu_check --device {cpu,cuda} [--quick] [--domains D ...] [--parts P ...]
[--params params.yaml] [--profile paper] [--root .] [--threads N] [--compile] [--json FILE]``

Parts, for each domain (the network: ``pretrain.<domain>.model`` of the profile, seeded random weights):

* ``pretrain``: pretraining steps at ``pretrain.<domain>.train.batch_size`` on programs of the profile's
  synthetic sampler, executed as pretraining executes them (on the device, or by ``loader_workers`` processes),
  grouped by length (``bucket_pool``), under the profile's ``precision``; also the sampler's and the CPU
  executor's programs per second, the step's GFLOP per shape, and how many loader workers keep up;
* ``round``: one PLAD round (:func:`plad.learn.rounds.run_rounds`, LEST+ST+WS) on a handful of target shapes:
  beam inference into P_BEST, the wake-sleep generator's training and sampling, training epochs with their
  validation, the round's validation, each timed;
* ``st``, ``lest``, ``ws``: fine-tuning steps at ``finetune.<domain>.plad.train.batch_size`` on each source
  of that round (P_BEST's real shapes, its executions, the generator's samples);
* ``rl``: one REINFORCE optimizer step (``rl.accumulate`` batches of ``rl.batch_size``);
* ``beam10``: best-of-beam inference at beam 10 (beam search, execution, metric) on a batch of
  ``evaluate.<domain>.batch_size`` shapes;
* ``agree`` (CUDA only): the same weights and batch on the CPU and on the GPU, in float32 (TF32 off): the
  loss within 1e-3 relative and the same greedy programs (a program may part at a near-tie of two logits,
  counted and shown); and the bf16 loss within :data:`plad.device.BF16_LOSS_RTOL` of the float32 one;
* ``compile`` (with ``--compile``): pretraining steps with the encoder compiled against eager ones.

``--quick`` keeps the paper's network but shrinks every batch (pretraining and fine-tuning 8, RL 2, beam 2
shapes, a round on 6 shapes) and times one step after one warm-up step: the check that every part runs, within
minutes on a CPU. Target shapes are the prepared training shapes of ``--root`` (``data/prepared/<domain>.npz``)
when there, else executions of sampled programs. Then estimates of the paper profile's hours per stage on this
device follow from the measured throughputs (docs/gpu.md says how). The last line is
``paper profile: <k> parts ok on <device>`` (and what failed); the exit status is 1 if any part failed.
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

PARTS = ("pretrain", "round", "st", "lest", "ws", "rl", "beam10", "agree", "compile")
#: parts that train on the round's P_BEST and wake-sleep samples
NEEDS_ROUND = ("st", "lest", "ws")
#: relative loss difference allowed between the CPU and a GPU in float32
FP32_LOSS_RTOL = 1e-3
#: a greedy program that parts between the CPU and a GPU where the two tokens' logits are closer than this (on
#: the CPU) is a near-tie, not a disagreement: float32 sums in another order move logits by ~1e-6
TIE = 1e-3
#: synthetic programs the paper pretrains on to convergence (supplement: 3D CSG 40 epochs, ShapeAssembly 26
#: epochs of its 2 M programs); 2D CSG took CSGNet's pretrained weights, so the paper gives no figure
PAPER_PRETRAIN_SHAPES = {"csg3d": 40 * 2_000_000, "shapeassembly": 26 * 2_000_000}
GIB = 2 ** 30


@dataclass
class Sizes:
    """How big each part is in one run (the paper profile's sizes, or ``--quick``'s)."""

    pretrain_batch: int
    plad_batch: int
    rl_batch: int
    rl_accumulate: int
    beam_shapes: int
    round_train: int
    round_val: int
    ws_sample_batch: int
    warmup: int
    steps: int
    agree_shapes: int
    quick: bool


def sizes_for(pre, ft, ev, quick: bool) -> Sizes:
    if quick:
        return Sizes(pretrain_batch=8, plad_batch=8, rl_batch=2, rl_accumulate=1, beam_shapes=2, round_train=6,
                     round_val=3, ws_sample_batch=16, warmup=1, steps=1, agree_shapes=4, quick=True)
    return Sizes(pretrain_batch=pre.train.batch_size, plad_batch=ft.plad.train.batch_size,
                 rl_batch=ft.rl.batch_size, rl_accumulate=ft.rl.accumulate, beam_shapes=ev.batch_size,
                 round_train=ft.plad.infer_batch, round_val=20, ws_sample_batch=ft.plad.ws.sample_batch, warmup=1,
                 steps=3, agree_shapes=16, quick=False)


@dataclass
class Result:
    domain: str
    part: str
    ok: bool = False
    #: items (shapes, programs) processed in the timed work, its wall-clock seconds and this process's CPU seconds
    #: (all threads; on a machine shared with other work the wall clock says more about the other work)
    items: int = 0
    seconds: float = math.nan
    cpu_seconds: float = math.nan
    unit: str = "shapes"
    peak_bytes: int | None = None
    note: str = ""
    error: str = ""
    #: numbers the estimates use (rates per second, counts)
    values: dict[str, float] = field(default_factory=dict)

    @property
    def rate(self) -> float:
        return self.items / self.seconds if self.seconds and self.seconds > 0 else math.nan

    def speed(self, per_cpu: bool) -> float:
        """Items per wall-clock second, or per CPU second of this process (``per_cpu``)."""
        seconds = self.cpu_seconds if per_cpu else self.seconds
        return self.items / seconds if seconds and seconds > 0 else math.nan

    def value(self, key: str, per_cpu: bool) -> float:
        """A rate of :attr:`values`, per wall-clock second or per CPU second (``<key>_cpu``)."""
        return self.values[f"{key}_cpu" if per_cpu else key]

    def line(self) -> str:
        status = "ok" if self.ok else "FAILED"
        rate = ""
        if self.items:
            rate = f"{figure(self.rate)} {self.unit}/s"
            if self.cpu_seconds > 0:
                rate += f" ({figure(self.items / self.cpu_seconds)} per CPU second)"
        peak = f"peak {self.peak_bytes / GIB:.2f} GiB" if self.peak_bytes is not None else ""
        text = "  ".join(x for x in (f"{self.domain:13s} {self.part:8s} {status:6s}", rate, peak, self.note) if x)
        return text + (f"  {self.error}" if self.error else "")


class PeakMemory:
    """Peak memory while a part runs: CUDA's allocator peak on a GPU; on the CPU the process's resident set,
    sampled every 10 ms (Linux's /proc; elsewhere the process's lifetime peak)."""

    def __init__(self, device: torch.device):
        self.device, self.peak = device, None
        self._stop = threading.Event()

    @staticmethod
    def rss() -> int | None:
        try:
            with open("/proc/self/statm") as fh:
                return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, IndexError):
            import resource

            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    def _sample(self) -> None:
        while not self._stop.wait(0.01):
            value = self.rss()
            if value is not None:
                self.peak = max(self.peak or 0, value)

    def __enter__(self) -> PeakMemory:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
        else:
            self.peak = self.rss()
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak = torch.cuda.max_memory_allocated(self.device)
        else:
            self._stop.set()
            self._thread.join()
            value = self.rss()
            self.peak = max(self.peak or 0, value or 0)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def figure(x: float) -> str:
    """Three significant digits, thousands separated."""
    if not math.isfinite(x) or x == 0:
        return f"{x:g}"
    digits = max(0, 2 - int(math.floor(math.log10(abs(x)))))
    return f"{x:,.{digits}f}"


class Timer:
    """Wall-clock and CPU seconds (this process, all threads) of the timed work, summed over its uses; the
    device's queue is drained at both ends."""

    def __init__(self, device: torch.device):
        self.device, self.seconds, self.cpu_seconds = device, 0.0, 0.0

    def __enter__(self) -> Timer:
        sync(self.device)
        self._t0, self._c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc) -> None:
        sync(self.device)
        self.seconds += time.perf_counter() - self._t0
        self.cpu_seconds += time.process_time() - self._c0


def rows_of(programs: list[list[int]], max_len: int) -> torch.Tensor:
    """-1-padded token rows (N, max_len), as the synthetic file holds them."""
    out = torch.full((len(programs), max_len), -1, dtype=torch.long)
    for i, p in enumerate(programs):
        out[i, :len(p)] = torch.tensor(p)
    return out


@dataclass
class Context:
    """What every part of one domain gets."""

    domain: object
    device: torch.device
    sizes: Sizes
    pre: object
    ft: object
    ev: object
    sampler: Callable
    sampler_name: str
    base_state: dict
    model_config: object
    targets: np.ndarray
    target_source: str
    tmp: Path
    counts: dict[str, int]
    round_dir: Path | None = None

    def model(self, train: bool = True, device: torch.device | None = None):
        """A fresh copy of the domain's network (the same seeded weights for every part) on the device."""
        from plad.model.network import PLADNet

        model = PLADNet(self.model_config)
        model.load_state_dict(self.base_state)
        return model.to(device or self.device).train(train)


# ---- the parts ------------------------------------------------------------------------------------------------

def pretrain_batches(ctx: Context, rows: torch.Tensor, n: int, pool=None):
    """``n`` pretraining batches of ``rows`` as :func:`plad.learn.pretrain.pretrain` makes them: a permutation
    in batches, grouped by length, executed in the process on the device or by the pool's workers."""
    from plad.data.batching import bucketed
    from plad.learn.synthetic import make_batch

    bs = ctx.sizes.pretrain_batch
    perm = torch.randperm(len(rows), generator=torch.Generator().manual_seed(0))
    chunks = (perm[i:i + bs].numpy() for i in range(0, len(perm) - bs + 1, bs))
    lengths = (rows >= 0).sum(1).numpy()
    idx = itertools.islice(bucketed(chunks, lengths, min(ctx.pre.train.bucket_pool, n), np.random.default_rng(0)), n)
    stream = (rows[torch.from_numpy(i)] for i in idx)
    return pool.batches(stream, ctx.device) if pool is not None else (make_batch(ctx.domain, r, ctx.device)
                                                                      for r in stream)


def sample_rows(ctx: Context, n: int, seed: int) -> tuple[torch.Tensor, Timer]:
    """``n`` programs of the profile's sampler as rows, and the sampling's time."""
    from plad.device import torch_threads

    # one torch thread, as the synthesize stage samples (plad.device.torch_threads): on a many-core machine
    # the default threads multiplied the sampler's CPU seconds (docs/gpu.md)
    with torch_threads(1), Timer(torch.device("cpu")) as timer:
        programs = ctx.sampler(n, np.random.default_rng(seed))
    return rows_of(programs, ctx.domain.tokens.max_len), timer


def step_flops(model, batch, precision) -> float:
    """Floating-point operations of one training step's forward and backward pass on ``batch`` (matrix products,
    convolutions, attention: torch's FLOP counter)."""
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with counter:
        with precision.autocast():
            loss, _ = model.loss(*batch)
        loss.backward()
    model.zero_grad(set_to_none=True)
    return float(counter.get_total_flops())


def time_steps(ctx: Context, model, batches, precision, res: Result, lr: float, grad_clip) -> list[float]:
    """Warm-up and timed :func:`plad.learn.train.train_step` calls on ``batches`` (an iterator); fills ``res``
    (items, seconds); returns the timed steps' losses."""
    from plad.learn.train import train_step

    opt = torch.optim.Adam(model.parameters(), lr=lr)
    for _ in range(ctx.sizes.warmup):
        train_step(model, opt, lambda b: model.loss(*b), next(batches), grad_clip, precision)
    losses = []
    # the steps one after another as in training, the batches made between them; the GPU is waited for once
    with Timer(ctx.device) as timer:
        for _ in range(ctx.sizes.steps):
            batch = next(batches)
            loss, _ = train_step(model, opt, lambda b: model.loss(*b), batch, grad_clip, precision)
            losses.append(loss)
            res.items += len(batch[0])
    res.seconds, res.cpu_seconds = timer.seconds, timer.cpu_seconds
    return [float(x) for x in losses]


def part_pretrain(ctx: Context, res: Result) -> None:
    from plad.device import resolve_precision
    from plad.learn.synthetic import ExecutorPool, make_batch

    s = ctx.sizes
    n = s.warmup + s.steps
    # at least 128 programs, so that the sampler's rate is not its first few programs'
    rows, sampling = sample_rows(ctx, max(s.pretrain_batch * n, 128), seed=0)
    precision = resolve_precision(ctx.pre.precision, ctx.device)
    model = ctx.model()
    # --quick: at most 2 loader workers (the pool's path is run; the profile's count is for a GPU machine's cores)
    workers = min(ctx.pre.loader_workers, 2) if s.quick else ctx.pre.loader_workers
    pool = ExecutorPool(ctx.domain.name, workers) if workers else None
    try:
        losses = time_steps(ctx, model, pretrain_batches(ctx, rows, n, pool), precision, res, ctx.pre.train.lr,
                            ctx.pre.train.grad_clip)
    finally:
        if pool is not None:
            pool.close()
    # the executor alone, in this process on the CPU (a loader worker's rate; one thread, as a worker), on a
    # batch of the pretraining's size or 128 programs, whichever is more
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    executed = rows[:max(s.pretrain_batch, 128)]
    try:
        with Timer(torch.device("cpu")) as executing:
            make_batch(ctx.domain, executed, torch.device("cpu"))
    finally:
        torch.set_num_threads(threads)
    flops = step_flops(model, make_batch(ctx.domain, rows[:s.pretrain_batch], ctx.device), precision)
    per_shape = flops / s.pretrain_batch
    # the sampler and the executor run on one core: their programs per CPU second are what a core does
    sample_rate, exec_rate = len(rows) / sampling.cpu_seconds, len(executed) / executing.cpu_seconds
    # What a run sustains. With workers: on a GPU the steps' rate or what the workers execute, whichever is lower
    # (a few steps after a warm-up hide a slow pool: it executed them side by side before they were due); per CPU
    # second, the executions' CPU time added to the steps' (the workers' time is not this process's).
    sustained = min(res.rate, workers * exec_rate) if workers else res.rate
    sustained_cpu = 1 / (1 / res.speed(True) + 1 / exec_rate) if workers else res.speed(True)
    res.values.update(sample_rate=sample_rate, sample_rate_cpu=sample_rate, exec_rate=exec_rate,
                      exec_rate_cpu=exec_rate, sustained=sustained, sustained_cpu=sustained_cpu,
                      flops_per_shape=per_shape)
    need = math.ceil(res.rate / exec_rate) if exec_rate > 0 else 0
    where = f"{workers} loader workers" if workers else "executed in the training process"
    on_cpu = ctx.device.type == "cpu"
    tflops = f"{figure(per_shape * res.speed(on_cpu) / 1e12)} TFLOP/s" + (" per CPU second" if on_cpu else "")
    res.note = (f"batch {s.pretrain_batch} x {s.steps} step(s), {1e3 * res.seconds / s.steps:.0f} ms/step, "
                f"{precision.name}, loss {np.mean(losses):.3f}; {per_shape / 1e9:.2f} GFLOP/shape ({tflops}); "
                f"sampler {ctx.sampler_name} {figure(sample_rate)} programs/s per core; CPU executor "
                f"{figure(exec_rate)} programs/s per core: {where}, {need} worker(s) would keep up"
                + (f"; sustained {figure(sustained)} shapes/s" if sustained < res.rate else ""))


def part_compile(ctx: Context, res: Result) -> None:
    """Pretraining steps with the encoder compiled (params ``pretrain.compile``) against eager ones."""
    from plad.device import resolve_precision

    s = ctx.sizes
    n = s.warmup + s.steps
    rows = sample_rows(ctx, s.pretrain_batch * n, seed=0)[0]
    precision = resolve_precision(ctx.pre.precision, ctx.device)
    eager = Result(ctx.domain.name, "eager")
    time_steps(ctx, ctx.model(), pretrain_batches(ctx, rows, n), precision, eager, ctx.pre.train.lr,
               ctx.pre.train.grad_clip)
    model = ctx.model()
    model.encoder.compile()
    start = time.perf_counter()
    time_steps(ctx, model, pretrain_batches(ctx, rows, n), precision, res, ctx.pre.train.lr, ctx.pre.train.grad_clip)
    res.note = (f"compiled encoder: {1e3 * res.seconds / s.steps:.0f} ms/step against eager "
                f"{1e3 * eager.seconds / s.steps:.0f} ms/step (x{eager.seconds / res.seconds:.2f}); compiling and "
                f"warm-up {time.perf_counter() - start - res.seconds:.0f} s")


class StepTimes:
    """:class:`plad.learn.rounds.RoundHooks`'s ``step``: runs every step of a round, timing it."""

    def __init__(self, device: torch.device):
        self.device = device
        self.timers: dict[str, Timer] = {}

    def __call__(self, name: str, fn, *args, **kwargs):
        key = name.split(": ", 1)[-1]
        with self.timers.setdefault(key, Timer(self.device)):
            return fn(*args, **kwargs)


def part_round(ctx: Context, res: Result) -> None:
    from plad.device import resolve_precision
    from plad.learn.job import Job
    from plad.learn.methods import MethodConfig
    from plad.learn.rounds import RoundHooks, run_rounds

    s = ctx.sizes
    plad = ctx.ft.plad
    cfg = dataclasses.replace(
        plad, infer_batch=min(plad.infer_batch, s.round_train), max_rounds=1,
        train=dataclasses.replace(plad.train, batch_size=s.plad_batch, steps_per_epoch=s.steps, max_epochs=1),
        ws=dataclasses.replace(plad.ws, batch_size=s.plad_batch, max_epochs=1, steps_per_epoch=s.steps,
                               sample_batch=s.ws_sample_batch,
                               # an untrained generator draws many empty or repeated programs: --quick gives up sooner
                               max_sample_factor=3 if s.quick else plad.ws.max_sample_factor))
    train, val = ctx.targets[:s.round_train], ctx.targets[s.round_train:s.round_train + s.round_val]
    out = ctx.tmp / f"round-{ctx.domain.name}"
    job = Job(ctx.model(), ctx.domain, train, val, out, seed=0,
              precision=resolve_precision(ctx.ft.precision, ctx.device))
    times = StepTimes(ctx.device)
    with Timer(ctx.device) as timer:
        summary = run_rounds(job, MethodConfig(method="lest+st+ws"), cfg, RoundHooks(step=times))
    total = timer.seconds
    infer = times.timers["infer"]
    res.items, res.seconds, res.cpu_seconds = len(train), total, timer.cpu_seconds
    res.values.update(infer_rate=len(train) / infer.seconds, infer_rate_cpu=len(train) / infer.cpu_seconds)
    # the round's steps, after the validation of the model it starts from (not a step of a round)
    seconds = {k: t.seconds for k, t in times.timers.items()}
    steps = ", ".join(f"{k} {v:.1f} s" for k, v in
                      {"start validation": total - sum(seconds.values()), **seconds}.items())
    res.note = (f"{len(train)} training, {len(val)} validation shapes ({ctx.target_source}): {total:.1f} s in all; "
                f"{steps}; inference at beam {cfg.infer_beam}: {figure(len(train) / infer.seconds)} shapes/s; "
                f"rounds {summary['units']}")
    ctx.round_dir = out


def part_source(name: str) -> Callable[[Context, Result], None]:
    """Fine-tuning steps on one source of the round: ``st``, ``lest`` or ``ws``."""

    def run(ctx: Context, res: Result) -> None:
        from plad.device import resolve_precision
        from plad.learn.methods import Mixture, lest_source, mixture_batches, st_source
        from plad.learn.pbest import PBest
        from plad.learn.ws import ws_source

        if ctx.round_dir is None:
            raise RuntimeError("needs the round's P_BEST, and the round did not run")
        s = ctx.sizes
        if name == "ws":
            with np.load(ctx.round_dir / "ws_round_001.npz") as z:
                programs = z["programs"]
                executions = np.unpackbits(z["executions"], axis=1, count=int(np.prod(ctx.domain.shape)))
            source = ws_source(programs, executions.astype(bool).reshape(-1, *ctx.domain.shape), ctx.device)
        else:
            pbest = PBest.load(ctx.round_dir / "pbest.npz", ctx.domain.metric, ctx.domain.canonical)
            source = (st_source(pbest, ctx.targets[:s.round_train], ctx.device) if name == "st"
                      else lest_source(pbest, ctx.device))
        plad = ctx.ft.plad.train
        batches = mixture_batches(Mixture((name,), (1.0,)), {name: source}, s.plad_batch, seed=0,
                                  bucket_pool=plad.bucket_pool)(0)
        precision = resolve_precision(ctx.ft.precision, ctx.device)
        losses = time_steps(ctx, ctx.model(), batches, precision, res, plad.lr, plad.grad_clip)
        res.note = (f"batch {s.plad_batch} x {s.steps} step(s), {1e3 * res.seconds / s.steps:.0f} ms/step, "
                    f"{precision.name}, loss {np.mean(losses):.3f}")
    return run


def part_rl(ctx: Context, res: Result) -> None:
    from plad.device import resolve_precision, to_device
    from plad.learn.rl import Reinforce

    s = ctx.sizes
    cfg = dataclasses.replace(ctx.ft.rl, batch_size=s.rl_batch, accumulate=s.rl_accumulate)
    precision = resolve_precision(ctx.ft.precision, ctx.device)
    learner = Reinforce(ctx.model(), ctx.domain, cfg, seed=0, precision=precision)
    rng = np.random.default_rng(0)
    timer = Timer(ctx.device)
    for i in range(s.warmup + 1):   # warm-up optimizer steps, then one timed
        with timer if i == s.warmup else Timer(ctx.device):
            for _ in range(cfg.accumulate):
                shapes = to_device(ctx.targets[rng.choice(len(ctx.targets), size=cfg.batch_size)], ctx.device)
                stats = learner.step(shapes)
    res.items, res.seconds, res.cpu_seconds = cfg.batch_size * cfg.accumulate, timer.seconds, timer.cpu_seconds
    res.note = (f"one optimizer step of {cfg.accumulate} batch(es) of {cfg.batch_size} (sample, execute, "
                f"reward, backward), {precision.name}: {res.seconds:.2f} s; reward {stats['reward']:.3f}")


def part_beam(ctx: Context, res: Result) -> None:
    from plad.device import to_device
    from plad.model.decode import infer_programs

    s = ctx.sizes
    model = ctx.model(train=False)
    shapes = to_device(ctx.targets[:s.beam_shapes], ctx.device)
    if not s.quick:   # a warm-up call
        infer_programs(model, ctx.domain, shapes[:2], 10)
    with Timer(ctx.device) as timer:
        inferred = infer_programs(model, ctx.domain, shapes, 10)
    res.items, res.seconds, res.cpu_seconds = len(shapes), timer.seconds, timer.cpu_seconds
    lengths = inferred.beam.lengths.float().mean()
    res.note = (f"{len(shapes)} shapes, beam 10 (search, execution, metric): {timer.seconds:.2f} s; untrained "
                f"network: programs of {float(lengths):.0f} tokens on average")


def greedy_agreement(cpu_model, gpu_model, table, shapes: torch.Tensor) -> tuple[int, int, int]:
    """(identical programs, programs that part at a near-tie, programs that part elsewhere) of greedy decoding
    on the CPU and on the GPU."""
    from plad.model.decode import greedy_decode

    on_cpu = greedy_decode(cpu_model, table, shapes)
    on_gpu = greedy_decode(gpu_model, table, shapes.cuda())
    same = ties = other = 0
    for i, (a, b) in enumerate(zip(on_cpu, on_gpu)):
        if a == b:
            same += 1
            continue
        k = next((j for j, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
        if k >= min(len(a), len(b)):
            other += 1   # one is a prefix of the other: never a tie
            continue
        tokens_in = torch.tensor([[cpu_model.cfg.bos, *a[:k]]])
        with torch.no_grad():
            logits = cpu_model(shapes[i:i + 1], tokens_in)[0, -1]
        if abs(float(logits[a[k]] - logits[b[k]])) < TIE:
            ties += 1
        else:
            other += 1
    return same, ties, other


def part_agree(ctx: Context, res: Result) -> None:
    from plad.device import BF16_LOSS_RTOL, resolve_precision
    from plad.learn.synthetic import make_batch

    if ctx.device.type != "cuda":
        raise RuntimeError("agreement is a CUDA check")
    n = ctx.sizes.agree_shapes
    rows = sample_rows(ctx, n, seed=2)[0]
    cpu = torch.device("cpu")
    batch = make_batch(ctx.domain, rows, cpu)
    cpu_model = ctx.model(train=False, device=cpu)
    gpu_model = ctx.model(train=False)
    gpu_batch = tuple(t.to(ctx.device) for t in batch)
    gpu_exec = ctx.domain.execute(batch[1].to(ctx.device)).cpu()
    tf32 = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        with torch.no_grad():
            cpu_loss = float(cpu_model.loss(*batch)[0])
            gpu_loss = float(gpu_model.loss(*gpu_batch)[0])
            with resolve_precision("bf16", ctx.device).autocast():
                bf16_loss = float(gpu_model.loss(*gpu_batch)[0])
        same, ties, other = greedy_agreement(cpu_model, gpu_model, ctx.domain.tokens, batch[0][:max(2, n // 2)])
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = tf32
    rel, rel16 = abs(gpu_loss - cpu_loss) / cpu_loss, abs(bf16_loss - cpu_loss) / cpu_loss
    problems = []
    if not torch.equal(gpu_exec, batch[0]):
        problems.append("the executor's GPU shapes differ from its CPU shapes")
    if rel >= FP32_LOSS_RTOL:
        problems.append(f"fp32 loss differs by {rel:.1e} (limit {FP32_LOSS_RTOL:.0e})")
    if rel16 >= BF16_LOSS_RTOL:
        problems.append(f"bf16 loss differs by {rel16:.1e} (limit {BF16_LOSS_RTOL:.0e})")
    if other:
        problems.append(f"{other} greedy program(s) differ beyond a near-tie")
    res.note = (f"{n} shapes: executions equal {torch.equal(gpu_exec, batch[0])}; loss CPU {cpu_loss:.6f}, GPU fp32 "
                f"{gpu_loss:.6f} (rel. {rel:.1e}), GPU bf16 {bf16_loss:.6f} (rel. {rel16:.1e}); greedy programs: "
                f"{same} identical, {ties} part at a near-tie (< {TIE:g}), {other} differ")
    if problems:
        raise AssertionError("; ".join(problems))


RUNNERS: dict[str, Callable[[Context, Result], None]] = {
    "pretrain": part_pretrain, "round": part_round, "st": part_source("st"), "lest": part_source("lest"),
    "ws": part_source("ws"), "rl": part_rl, "beam10": part_beam, "agree": part_agree, "compile": part_compile}


def run_part(ctx: Context, part: str) -> Result:
    res = Result(ctx.domain.name, part)
    try:
        with PeakMemory(ctx.device) as peak:
            RUNNERS[part](ctx, res)
        res.peak_bytes, res.ok = peak.peak, True
    except Exception as err:   # a failing part is reported, and the others still run
        res.error = f"{type(err).__name__}: {' '.join(str(err).split())}"
        if os.environ.get("PLAD_GPU_CHECK_TRACEBACK"):
            traceback.print_exc()
        if ctx.device.type == "cuda":
            torch.cuda.empty_cache()
    return res


# ---- estimates ---------------------------------------------------------------------------------------------

def estimates(domain: str, results: dict[str, Result], pre, ft, syn, counts: dict[str, int], sizes: Sizes,
              per_cpu: bool) -> list[str]:
    """The paper profile's hours per stage on this device, from this run's throughputs (see docs/gpu.md): per
    wall-clock second on a GPU, per CPU second on the CPU (``per_cpu``: a shared machine's wall clock says more
    about the other work)."""
    out = []
    pretrain = results.get("pretrain")
    if pretrain is not None and pretrain.ok:
        sample = pretrain.value("sample_rate", per_cpu)
        out.append(f"synthesize {syn.train_programs:,} programs: {figure(syn.train_programs / sample / 3600)} h in one "
                   f"process")
        rate = pretrain.value("sustained", per_cpu)
        epoch = pre.train.steps_per_epoch * pre.train.batch_size
        text = (f"pretrain at {figure(rate)} shapes/s (batch {sizes.pretrain_batch}): an epoch of {epoch:,} shapes "
                f"{figure(epoch / rate / 3600)} h")
        if domain in PAPER_PRETRAIN_SHAPES:
            shapes = PAPER_PRETRAIN_SHAPES[domain]
            text += f"; the paper's {shapes / 1e6:.0f} M shapes to convergence {figure(shapes / rate / 3600)} h"
        else:
            epochs = pre.train.patience + 1
            text += f"; the least early stopping allows ({epochs} epochs) {figure(epochs * epoch / rate / 3600)} h"
        out.append(text)
    rnd = results.get("round")
    steps = [results[k] for k in ("st", "lest") if k in results and results[k].ok]
    if rnd is not None and rnd.ok and steps and "train" in counts and "val" in counts:
        infer_rate = rnd.value("infer_rate", per_cpu)
        infer_h = counts["train"] / infer_rate / 3600
        step_rate = np.mean([r.speed(per_cpu) for r in steps])
        plad = ft.plad.train
        train_h = plad.steps_per_epoch * plad.batch_size / step_rate / 3600
        # the epoch's validation is at beam val_beam_epoch (3); costed at the inference rate (beam 5): an upper bound
        val_h = counts["val"] / infer_rate / 3600
        epochs = plad.patience + 1
        round_h = infer_h + epochs * (train_h + val_h)
        out.append(f"finetune, a PLAD round: inference over {counts['train']:,} shapes at beam {ft.plad.infer_beam} "
                   f"{figure(infer_h)} h; a training epoch ({plad.steps_per_epoch} steps of {plad.batch_size}) "
                   f"{figure(train_h)} h and its validation on {counts['val']:,} shapes {figure(val_h)} h; a round of "
                   f"{epochs} epochs (the least patience {plad.patience} allows) {figure(round_h)} h (LEST+ST; WS adds "
                   f"its generator)")
    beam = results.get("beam10")
    if beam is not None and beam.ok and "test" in counts:
        hours = counts["test"] / beam.speed(per_cpu) / 3600
        out.append(f"evaluate {counts['test']:,} test shapes at beam 10: {figure(hours)} h")
    return [f"{domain:13s} {line}" for line in out]


# ---- main --------------------------------------------------------------------------------------------------

def prepared_counts(root: Path, domain: str) -> dict[str, int]:
    """Shapes per split of the prepared real data (``data/prepared/<domain>.json``, committed), if known."""
    from plad.layout import Layout

    path = Layout(root).prepared_summary(domain)
    if not path.exists():
        return {}
    data = json.loads(path.read_text())
    return {s: int(data[f"{s}_count"]) for s in ("train", "val", "test") if f"{s}_count" in data}


def targets_for(domain, root: Path, n: int, sampler) -> tuple[np.ndarray, str]:
    """``n`` target shapes: the prepared training shapes (evenly spaced) when there, else executions of
    sampled programs."""
    from plad.data.files import load_split
    from plad.domains.base import pad_programs
    from plad.layout import Layout

    prepared = Layout(root).prepared(domain.name)
    if prepared.exists():
        return load_split(prepared, "train", n)[0], f"prepared training shapes of {prepared}"
    programs = sampler(n, np.random.default_rng(1))
    return domain.execute(pad_programs(programs)).numpy(), "executions of sampled programs"


def main(argv: list[str] | None = None) -> int:
    from plad.config import ConfigError, load_params, section
    from plad.device import resolve_device
    from plad.domains import get_domain
    from plad.learn.pretrain import PretrainConfig
    from plad.model.network import ModelConfig, PLADNet, count_parameters
    from plad.stages.evaluate import EvaluateConfig
    from plad.stages.finetune import FinetuneStageConfig
    from plad.stages.synthesize import SynthesizeConfig

    parser = argparse.ArgumentParser(prog="python -m bench.gpu_check", description=__doc__.splitlines()[0])
    parser.add_argument("--device", choices=("cpu", "cuda"), required=True)
    parser.add_argument("--quick", action="store_true", help="small batches, one timed step: every part runs")
    parser.add_argument("--domains", nargs="+", default=None, help="default: the params' domains")
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=None,
                        help="default: every part (agree on CUDA only; compile only with --compile)")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--root", default=".", help="layout root whose prepared shapes are the targets, if there")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads (default: torch's; 1 with --quick on the CPU)")
    parser.add_argument("--compile", action="store_true", help="also time the encoder under torch.compile")
    parser.add_argument("--json", default=None, help="also write every part's figures to this file")
    args = parser.parse_args(argv)
    try:
        device = resolve_device(args.device)
        params = load_params(args.params, profile=args.profile)
    except ConfigError as err:
        print(f"{parser.prog}: error: {err}", file=sys.stderr)
        return 1
    if args.threads:
        torch.set_num_threads(args.threads)
    elif args.quick and device.type == "cpu":
        # a check that every part runs, not of speed: one thread, whose CPU time is what a core does (on a shared
        # machine, OpenMP threads waiting for each other cost more than they give)
        torch.set_num_threads(1)
    domains = args.domains or params["domains"]
    from plad.domains import domain_names

    unknown = [d for d in domains if d not in domain_names()]
    if unknown:
        parser.error(f"unknown domain(s) {', '.join(unknown)}; known: {', '.join(domain_names())}")
    parts = set(args.parts or [p for p in PARTS if p != "compile"]) | ({"compile"} if args.compile else set())
    if device.type != "cuda":
        parts.discard("agree")   # nothing to agree with
    if parts & set(NEEDS_ROUND):
        parts.add("round")   # they train on its P_BEST
    parts = sorted(parts, key=PARTS.index)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{os.cpu_count()} CPU cores"
    print(f"paper-profile check on {device.type} ({name}), torch {torch.__version__}, {torch.get_num_threads()} "
          f"CPU thread(s), profile {args.profile}{', quick' if args.quick else ''}; parts: {' '.join(parts)}",
          flush=True)
    results: list[Result] = []
    lines: list[str] = []
    wall = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="plad-gpu-check-") as tmp:
        for d in domains:
            domain = get_domain(d)
            pre = section(params, f"pretrain.{d}", PretrainConfig)
            ft = section(params, f"finetune.{d}", FinetuneStageConfig)
            ev = section(params, f"evaluate.{d}", EvaluateConfig)
            syn = section(params, f"synthesize.{d}", SynthesizeConfig)
            sizes = sizes_for(pre, ft, ev, args.quick)
            sampler = domain.samplers()[syn.sampler]
            n_targets = max(sizes.round_train + sizes.round_val, sizes.beam_shapes)
            targets, source = targets_for(domain, Path(args.root), n_targets, sampler)
            torch.manual_seed(0)
            config = ModelConfig.for_domain(pre.model, domain)
            state = PLADNet(config).state_dict()
            print(f"{d}: {count_parameters(PLADNet(config)):,} parameters (width {pre.model.d_model}, "
                  f"{pre.model.n_layers} layers, {pre.model.n_heads} heads, encoder {list(pre.model.enc_channels)}); "
                  f"targets: {source}", flush=True)
            ctx = Context(domain, device, sizes, pre, ft, ev, sampler, syn.sampler, state, config, targets, source,
                          Path(tmp), prepared_counts(Path(args.root), d))
            done: dict[str, Result] = {}
            for part in parts:
                res = run_part(ctx, part)
                done[part] = res
                results.append(res)
                print(res.line(), flush=True)
            lines += estimates(d, done, pre, ft, syn, ctx.counts, sizes, per_cpu=device.type == "cpu")
    if lines:
        basis = "per CPU second: hours of one core" if device.type == "cpu" else "per wall-clock second"
        print(f"estimates for this device, not measurements (this run's throughput, {basis}, times the "
              f"{args.profile} profile's sizes; docs/gpu.md):")
        print("\n".join(lines))
    ok = [r for r in results if r.ok]
    failed = [f"{r.domain} {r.part}" for r in results if not r.ok]
    if args.json:
        from plad.fsutil import atomic_write_text

        atomic_write_text(args.json, json.dumps({
            "device": device.type, "device_name": name, "torch": torch.__version__, "quick": args.quick,
            "profile": args.profile, "seconds": round(time.perf_counter() - wall, 1),
            "results": [{**dataclasses.asdict(r), "rate": r.rate} for r in results], "estimates": lines},
            indent=2, default=float) + "\n")
    print(f"checked in {time.perf_counter() - wall:.0f} s")
    tail = f"; {len(failed)} failed: {', '.join(failed)}" if failed else ""
    print(f"paper profile: {len(ok)} parts ok on {device.type}{tail}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
