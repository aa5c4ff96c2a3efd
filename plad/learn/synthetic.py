"""Synthetic (shape, program) pairs for training: the programs of the ``synthesize`` stage, read from their
file, and batches whose shapes are executed on the fly: in the training process on its device
(:func:`make_batch`; CSG's executors run on a GPU), or ahead of time by worker processes on the CPU
(:class:`ExecutorPool`; ShapeAssembly's executor is Python, about 2 ms a program, which would keep a GPU waiting
for every batch).

Used by pretraining (:mod:`plad.learn.pretrain`) and its token-kind probe (:mod:`plad.tools.kind_gaps`).
"""
from __future__ import annotations

import collections
import multiprocessing
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch

from plad.config import ConfigError
from plad.data.batching import trim
from plad.device import to_device
from plad.domains.base import split_padding


def load_programs(path: Path) -> dict[str, torch.Tensor]:
    """``train``/``val`` token rows (N, L) int64, -1-padded, and their complexities where the file has them."""
    import zipfile

    from plad.data.files import DataError

    if not path.exists():
        raise ConfigError(f"{path}: synthetic programs not found; run the synthesize stage first")
    try:
        with np.load(path) as z:
            data = {k: torch.from_numpy(z[k].astype(np.int64))
                    for k in ("train", "val", "train_complexity", "val_complexity") if k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise DataError(path, f"not a readable synthetic .npz ({type(err).__name__}: {err}); run the synthesize "
                              "stage again") from None
    if "train" not in data or "val" not in data:
        raise DataError(path, "not a synthetic programs file (no train/val arrays); run the synthesize stage again")
    return data



def make_batch(domain, programs: torch.Tensor, device: torch.device) -> tuple[torch.Tensor, ...]:
    """(shapes, programs, lengths) from -1-padded token rows: shapes are executed here, on ``device``; the
    programs are cut to the longest one (:func:`plad.data.batching.trim`) where the rows are (the synthetic
    file's: on the CPU, so that a GPU is not waited for to read the longest length), then moved."""
    programs, lengths = split_padding(programs)
    programs = trim(programs, lengths)
    programs, lengths = to_device(programs, device), to_device(lengths, device)
    return domain.execute(programs), programs, lengths


# -- execution ahead of time in worker processes --------------------------------------------------------------
_WORKER_DOMAIN = None


def _start_worker(domain_name: str) -> None:
    global _WORKER_DOMAIN
    from plad.domains import get_domain

    torch.set_num_threads(1)   # one core per worker: the workers run side by side
    _WORKER_DOMAIN = get_domain(domain_name)


def _execute(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """In a worker: :func:`make_batch` of -1-padded rows on the CPU, as arrays (plainly pickled back)."""
    shapes, programs, lengths = make_batch(_WORKER_DOMAIN, torch.from_numpy(rows), torch.device("cpu"))
    return shapes.numpy(), programs.numpy(), lengths.numpy()


class ExecutorPool:
    """Worker processes that execute the synthetic programs of the next batches on the CPU while the model
    trains on the current one (params ``pretrain.<domain>.loader_workers``).

    :meth:`batches` gives exactly :func:`make_batch`'s batches, in order (the executors are deterministic, and
    a CPU execution equals a GPU one); each is copied to the device through pinned memory without blocking.
    Workers are started with ``spawn`` (they inherit neither a CUDA context nor the training process's
    threads) and get only the rows of each batch, never the whole synthetic set. Use as a context manager, or
    :meth:`close` it.
    """

    def __init__(self, domain_name: str, workers: int, ahead: int | None = None):
        self.workers = workers
        #: batches submitted ahead of the one being trained on
        self.ahead = ahead or 2 * workers
        self._pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_start_worker, initargs=(domain_name,))

    def batches(self, rows: Iterable[torch.Tensor], device: torch.device) -> Iterator[tuple[torch.Tensor, ...]]:
        """(shapes, programs, lengths) on ``device`` for every item of ``rows`` (-1-padded token rows (N, L)),
        in order; rows are taken ``ahead`` batches early (give a finite stream: what is taken is executed)."""
        source = iter(rows)
        pending: collections.deque[Future] = collections.deque()

        def submit() -> None:
            item = next(source, None)
            if item is not None:
                pending.append(self._pool.submit(_execute, np.ascontiguousarray(item.numpy())))

        for _ in range(self.ahead):
            submit()
        while pending:
            shapes, programs, lengths = pending.popleft().result()
            submit()
            yield to_device(shapes, device), to_device(programs, device), to_device(lengths, device)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ExecutorPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
