"""Data-parallel training over the processes of one run, started by ``torchrun`` (torch.distributed).

Every process (rank) runs the same trainer on the same files; the rules that
keep them in step live here, and the trainers call these helpers with a line
or two each:

* gradients: the model's loss goes through :func:`data_parallel` (PyTorch's
  ``DistributedDataParallel``), which averages the gradients over the ranks
  in the backward pass, so every rank takes the same optimizer step;
* data: each rank draws its own part of the batches, deterministically from
  (seed, epoch, rank): :func:`rank_seed` for independent streams,
  :func:`chunk_starts` for a shared permutation dealt out in turn. Rank 0's
  stream is the single-process stream. A batch size is per process: N
  processes see N times the data per step;
* decisions: :class:`plad.learn.loop.Loop` takes rank 0's unit value, time and
  limits by :func:`broadcast`, so early stopping and budgets never diverge;
* outputs: only rank 0 (:func:`is_main`) writes checkpoints, P_BEST, DVC
  outputs and MLflow runs; the other ranks read what it wrote (resuming, the
  best weights), so the output folder must be on a file system every node
  sees;
* shared work: :func:`map_split` splits work over shapes (beam inference)
  across the ranks and gathers the parts on every rank.

Outside ``torchrun`` (``WORLD_SIZE`` unset) the world is one process and every
helper is the identity: the single-process path computes exactly what it
computed before this module. The process group is created on first use:
gloo for CPU tensors, NCCL for CUDA tensors; each process uses the GPU of its
``LOCAL_RANK``.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import torch
import torch.distributed as tdist
from torch import nn

T = TypeVar("T")


def world() -> int:
    """Number of processes of this run (``WORLD_SIZE``, set by torchrun; 1 otherwise)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def rank() -> int:
    return int(os.environ.get("RANK", "0"))


def is_main() -> bool:
    """True on the process that writes outputs (rank 0; always in a single-process run)."""
    return rank() == 0


def init() -> None:
    """Join the process group of a torchrun launch (no-op in one process; idempotent).

    Call it before the model moves to a GPU: it makes ``LOCAL_RANK``'s GPU the
    current device, so that ``cuda`` means each process's own GPU.
    """
    if world() == 1 or tdist.is_initialized():
        return
    if torch.cuda.is_available():
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        backend = "cpu:gloo,cuda:nccl"   # objects and CPU tensors over gloo, gradients of GPU models over NCCL
    else:
        backend = "gloo"
    tdist.init_process_group(backend)


def broadcast(obj: T) -> T:
    """Rank 0's ``obj`` on every rank (any picklable object)."""
    if world() == 1:
        return obj
    init()
    box = [obj]
    tdist.broadcast_object_list(box, src=0)
    return box[0]


def all_gather(obj: T) -> list[T]:
    """Every rank's ``obj``, in rank order, on every rank."""
    if world() == 1:
        return [obj]
    init()
    out: list[Any] = [None] * world()
    tdist.all_gather_object(out, obj)
    return out


def mean(value: float) -> float:
    """The mean of ``value`` over the ranks (``value`` itself in one process)."""
    if world() == 1:
        return value
    init()
    t = torch.tensor([float(value)], dtype=torch.float64)
    tdist.all_reduce(t)
    return float(t[0]) / world()


def barrier() -> None:
    if world() > 1:
        init()
        tdist.barrier()


def main_first(fn: Callable[[], T]) -> T:
    """``fn()`` on rank 0, then on the other ranks (e.g. loading state that rank 0 may repair on disk first);
    no rank continues before all are done, so rank 0 writes nothing a late reader could see."""
    if world() == 1:
        return fn()
    out = fn() if is_main() else None
    barrier()
    if not is_main():
        out = fn()
    barrier()
    return out


def rank_seed(seed: int) -> int:
    """A seed for this rank's own stream: ``seed`` itself on rank 0 (the single-process stream), on the other
    ranks a seed derived from (seed, rank). Always in [0, 2**63)."""
    r = rank()
    if r == 0:
        return seed % 2**63
    return int(np.random.SeedSequence([seed % 2**63, r]).generate_state(1, np.uint64)[0]) >> 1


def chunk_starts(n: int, size: int) -> range:
    """Offsets of this rank's chunks of ``size`` in a sequence of ``n`` items dealt out to the ranks in turn.

    Rank r gets chunks r, r + N, r + 2N, ... of the complete chunks, and every
    rank gets as many (the tail that does not fill a chunk per rank is left
    out), so that the ranks take equally many steps. In one process: every
    complete chunk.
    """
    step = size * world()
    return range(rank() * size, n // step * step, step)


def split(n: int) -> np.ndarray:
    """This rank's contiguous part of ``range(n)`` (parts differ in length by at most one)."""
    return np.array_split(np.arange(n), world())[rank()]


def map_split(fn: Callable[[np.ndarray], T], n: int) -> list[T]:
    """``fn(indices)`` over this rank's :func:`split` of ``range(n)``; the results of all ranks, in order, on
    every rank. In one process: ``[fn(np.arange(n))]``."""
    return all_gather(fn(split(n)))


class _Call(nn.Module):
    """``forward(*args) = fn(module, *args)``: lets DDP see any loss function of ``module`` as a forward pass."""

    def __init__(self, module: nn.Module, fn: Callable[..., Any]):
        super().__init__()
        self.module, self.fn = module, fn

    def forward(self, *args: Any) -> Any:
        return self.fn(self.module, *args)


def data_parallel(module: nn.Module, fn: Callable[..., T]) -> Callable[..., T]:
    """``call(*args) = fn(module, *args)``, with the gradients of ``module``'s parameters averaged over the ranks
    in every backward pass through its result (DDP; every parameter must take part in ``fn``'s result).

    Creating it is a collective (rank 0's weights are copied to every rank): all
    ranks create it at the same point. In one process it is a plain call.
    """
    if world() == 1:
        return lambda *args: fn(module, *args)
    init()
    device = next(module.parameters()).device
    return nn.parallel.DistributedDataParallel(_Call(module, fn),
                                               device_ids=[device.index] if device.type == "cuda" else None)
