"""Search labels: a program for every real training shape, found by search from scratch (issue 58, step 1).

The labels are the teacher of the networks beyond the paper (:mod:`plad.learn.teach`): fixed
(shape, program) pairs on the real distribution. :func:`label_shapes` searches every shape of a
prepared split with the domain's search configuration (an effort level and overrides,
:func:`plad.rewrite.search_config`), in chunks run by a pool of one-thread worker processes
(:mod:`plad.rewrite.pool`). Each finished chunk is written atomically to ``<labels>/<domain>.parts/``,
so that a killed run, started again, searches only the unfinished chunks; the folder carries the
fingerprint of the work (config and prepared shapes) and a changed one starts afresh.

When every chunk is done the labels are gathered into ``<labels>/<domain>.npz`` (``index``: position
in the split; ``programs``: token ids (N, max_len) int16, -1 padded; ``values``: the metric of each
program against its shape; ``executions``: the executions, bit-packed) and a summary
``<labels>/<domain>.json`` (mean metric, cost per shape, tokens, provenance). Every program is
re-executed and re-scored in this process before the file is written, and a value that differs from
the search's own fails the stage: a label is exactly what its program draws.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from plad.config import ConfigError
from plad.fsutil import atomic_write, atomic_write_text, savez, sha256_file

#: the largest difference between a label's stored value and its re-executed one that counts as equal
RESCORE_TOLERANCE = 1e-9


@dataclass
class LabelConfig:
    """Params ``label.<domain>`` (stage ``label@<domain>``)."""

    domain: str = field(kw_only=True)
    #: the prepared split whose shapes are labelled
    split: str = "train"
    #: only the first N shapes of the labelling order, rounded up to whole chunks (null: all). The order is a
    #: fixed random permutation of the split, so any prefix is a uniform sample of it, and a run with a
    #: larger limit (or none) reuses the chunks of a smaller one and searches only the rest
    limit: int | None = None
    #: worker processes (one thread each)
    workers: int = 1
    #: shapes per chunk (the unit of a worker's work and of resuming)
    chunk: int = 128
    #: search configuration: an effort level and overrides (:func:`plad.rewrite.search_config`)
    search: dict = field(default_factory=lambda: {"effort": "default"})


@dataclass
class Labels:
    """A labelled split: what :func:`load_labels` returns."""

    domain: str
    index: np.ndarray                 # (N,) int64, positions in the prepared split
    programs: list[list[int]]         # N token lists
    values: np.ndarray                # (N,) float64
    executions: np.ndarray            # (N, *shape) bool

    def __len__(self) -> int:
        return len(self.index)


def labels_path(root: Path, domain: str) -> Path:
    return Path(root) / f"{domain}.npz"


def check(cfg: LabelConfig, domain, where: str) -> None:
    """Fail early (ConfigError naming ``where``) on a bad configuration."""
    from plad.rewrite import search_config

    if domain.rewrite is None:
        raise ConfigError(f"{where}: the {domain.name} domain has no search support")
    if cfg.workers < 1 or cfg.chunk < 1:
        raise ConfigError(f"{where}: workers ({cfg.workers}) and chunk ({cfg.chunk}) must be at least 1")
    if cfg.limit is not None and cfg.limit < 1:
        raise ConfigError(f"{where}.limit = {cfg.limit}: expected a positive number of shapes, or null")
    try:
        search_config(domain, **cfg.search)
    except (ConfigError, TypeError, ValueError) as err:
        raise ConfigError(f"{where}.search: {err}") from None


#: seed of the labelling order (:func:`order`)
ORDER_SEED = 58


def order(n: int) -> np.ndarray:
    """The labelling order of a split of ``n`` shapes: a fixed random permutation of its positions."""
    return np.random.default_rng([ORDER_SEED, n]).permutation(n)


def fingerprint(cfg: LabelConfig, prepared: Path) -> str:
    """What fixes each chunk's labels: the split, the chunks (order and size), the search configuration and the
    prepared file. Not the limit: a larger one only adds chunks."""
    work = {"domain": cfg.domain, "split": cfg.split, "order_seed": ORDER_SEED, "chunk": cfg.chunk,
            "search": cfg.search, "prepared": sha256_file(prepared)}
    return hashlib.sha256(json.dumps(work, sort_keys=True).encode()).hexdigest()[:16]


def label_shapes(cfg: LabelConfig, prepared: Path, out_root: Path, log=print) -> dict:
    """Search every shape of ``cfg.split`` of ``prepared``; write ``<out_root>/<domain>.npz`` and ``.json``.

    Resumable: finished chunks are read back from ``<out_root>/<domain>.parts/``. Returns the summary.
    """
    from plad.data.files import load_prepared
    from plad.domains import get_domain
    from plad.provenance import stamp
    from plad.rewrite import search_config
    from plad.rewrite.pool import Chunk, chunk_file, pad_programs, read_chunk, run_chunks, split, write_chunk

    started = time.monotonic()
    domain = get_domain(cfg.domain)
    where = f"label.{cfg.domain}"
    check(cfg, domain, where)
    shapes = load_prepared(prepared, cfg.split)
    index = order(len(shapes))
    if cfg.limit is not None:   # whole chunks of the order
        index = index[: min(len(index), math.ceil(cfg.limit / cfg.chunk) * cfg.chunk)]
    targets = shapes[index]
    shape = tuple(domain.shape)
    width = domain.tokens.max_len
    out_root = Path(out_root)
    parts = out_root / f"{cfg.domain}.parts"
    stamp_file = parts / "fingerprint.txt"
    key = fingerprint(cfg, prepared)
    if parts.exists() and (not stamp_file.exists() or stamp_file.read_text().strip() != key):
        log(f"{parts}: chunks of other work (config or shapes changed); starting afresh")
        shutil.rmtree(parts)
    parts.mkdir(parents=True, exist_ok=True)
    if not stamp_file.exists():
        atomic_write_text(stamp_file, key + "\n")

    pieces = split(len(targets), cfg.chunk)
    files = [chunk_file(parts, i) for i in range(len(pieces))]
    done = {i: read_chunk(files[i], shape) for i in range(len(pieces)) if files[i].exists()}
    todo = [i for i in range(len(pieces)) if i not in done]
    resumed = len(done)
    log(f"label {cfg.domain}: {len(targets)} shapes in {len(pieces)} chunks, {resumed} already done")
    by_first = {int(pieces[i][0]): i for i in todo}
    t0 = time.perf_counter()
    for r in run_chunks(cfg.domain, "search", [Chunk(pieces[i], targets[pieces[i]]) for i in todo],
                        cfg.search, cfg.workers):
        i = by_first[int(r.index[0])]
        write_chunk(files[i], r, width)
        done[i] = r
        log(f"label {cfg.domain}: chunk {i + 1}/{len(pieces)} mean {float(np.mean(r.values)):.4f} "
            f"{r.seconds / max(1, len(r.index)):.3f} s per shape ({len(done)}/{len(pieces)} done, "
            f"{time.perf_counter() - t0:.0f} s)")
    results = [done[i] for i in range(len(pieces))]
    programs = [p for r in results for p in r.programs]
    values = np.concatenate([r.values for r in results]) if results else np.zeros(0)
    executions = np.concatenate([r.executions for r in results]) if results else np.zeros((0, *shape), bool)
    seconds = float(sum(r.seconds for r in results))

    # every label re-executed and re-scored here: a stored value is exactly what its program draws
    rescored, redrawn = rescore(domain, programs, targets)
    worst = float(np.max(np.abs(rescored - values))) if len(values) else 0.0
    if worst > RESCORE_TOLERANCE or not np.array_equal(redrawn, executions):
        raise RuntimeError(f"{where}: a label's re-executed value differs from the search's by {worst:.3g}")

    lengths = np.array([len(p) for p in programs])
    summary = {
        "domain": cfg.domain, "split": cfg.split, "split_shapes": len(shapes), "metric": domain.metric.name,
        "higher_is_better": domain.metric.higher_is_better, "n": len(programs),
        "mean": round(float(values.mean()), 6) if len(values) else None,
        "empty_programs": int((lengths == 0).sum()),
        "mean_tokens": round(float(lengths.mean()), 2) if len(lengths) else None,
        "max_tokens": int(lengths.max()) if len(lengths) else 0,
        "rescored_max_difference": worst,
        # the search's own seconds per shape, one thread per worker (chunks of earlier, killed runs included)
        "search_seconds": round(seconds, 1),
        "seconds_per_shape": round(seconds / max(1, len(programs)), 4),
        "cpu_hours": round(seconds / 3600, 3),
        "chunks": len(pieces), "chunks_resumed": resumed, "workers": cfg.workers,
        "stopped_by_time": any(r.stopped_by_time for r in results),
        "config": asdict(search_config(domain, **cfg.search)),
        "fingerprint": key,
    }
    summary["provenance"] = stamp(cfg, started)
    buf = io.BytesIO()
    savez(buf, index=np.asarray(index, dtype=np.int64), programs=pad_programs(programs, width),
                        values=values.astype(np.float64),
                        executions=np.packbits(executions.reshape(len(programs), -1), axis=1),
                        domain=np.asarray(cfg.domain), split=np.asarray(cfg.split))
    atomic_write(labels_path(out_root, cfg.domain), lambda fh: fh.write(buf.getvalue()))
    atomic_write_text(out_root / f"{cfg.domain}.json", json.dumps(summary, indent=2) + "\n")
    return {k: v for k, v in summary.items() if k != "config"}


def rescore(domain, programs: list[list[int]], targets: np.ndarray, batch: int = 512
            ) -> tuple[np.ndarray, np.ndarray]:
    """(values (N,) float64, executions (N, *shape) bool) of ``programs[i]`` against ``targets[i]``."""
    import torch

    from plad.rewrite.evaluate import Scorer

    values = np.zeros(len(programs))
    executions = np.zeros((len(programs), *domain.shape), dtype=bool)
    for s in range(0, len(programs), batch):
        scorer = Scorer(domain, torch.from_numpy(np.asarray(targets[s:s + batch], dtype=bool)))
        chunk = programs[s:s + batch]
        values[s:s + batch] = scorer.values(chunk).numpy()
        executions[s:s + batch] = scorer.outputs(chunk).numpy()
    return values, executions


def load_labels(path: str | Path) -> Labels:
    """The labels of :func:`label_shapes`; a missing or damaged file is a one-line DataError."""
    from plad.data.files import DataError
    from plad.domains import get_domain
    from plad.rewrite.pool import unpad_programs

    path = Path(path)
    if not path.is_file():
        raise DataError(path, "no labels (run the stage label@<domain> first)")
    try:
        with np.load(path) as z:
            name = str(z["domain"])
            domain = get_domain(name)
            n = len(z["index"])
            executions = np.unpackbits(z["executions"], axis=1, count=int(np.prod(domain.shape)))
            return Labels(name, z["index"].astype(np.int64), unpad_programs(z["programs"]),
                          z["values"].astype(np.float64), executions.astype(bool).reshape(n, *domain.shape))
    except (OSError, ValueError, KeyError, EOFError) as err:
        raise DataError(path, f"not a labels file ({err})") from None
