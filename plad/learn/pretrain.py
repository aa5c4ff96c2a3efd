"""Supervised pretraining of p(z|x) on synthetic (shape, program) pairs.

Programs come from the ``synthesize`` stage; their shapes are executed on
the fly; batches group programs of similar length (``train.bucket_pool``,
:mod:`plad.data.batching`). Early stopping and the learning-rate schedule follow the
validation loss on the held-out synthetic programs; the greedy-decoding
metric on some of them is logged too. Resumable (see :mod:`plad.learn.train`).

Whether the network reads its input is logged every epoch
(:mod:`plad.learn.diagnostics`): ``prefix_gap``, the prefix-swap loss gap on the
first ``gap_programs`` validation programs, and ``real_val_<metric>``, the
greedy metric on ``real_val_shapes`` real validation shapes (evenly spaced
over the prepared ``val`` split). With ``curriculum.enabled`` the batches
follow :mod:`plad.learn.curriculum` (stage and per-stage validation in the
history: ``curriculum_stage``, ``stage_val_loss``, ``stage_val_acc``,
``stage_prefix_gap``: the same on the validation programs of the stage).

Outputs in ``runs/pretrain/<domain>/`` (:mod:`plad.layout`): ``best.pt``
(the model), ``last.pt`` (resume state), ``history.csv`` (per-epoch
metrics), ``summary.json``.

The stage ``pretrain`` (:mod:`plad.stages.pretrain`) runs it as an MLflow run.

Data-parallel on N processes with ``torchrun --nproc-per-node N -m
plad.stages.pretrain ...`` (:mod:`plad.learn.distributed`): the ranks deal out the
batches of each epoch's permutation in turn, and rank 0 writes the outputs.
"""
from __future__ import annotations

import csv
import json
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from plad.config import ConfigError
from plad.data.batching import bucketed
from plad.device import resolve_device
from plad.domains.base import pad_programs
from plad.fsutil import atomic_write_text
from plad.layout import HISTORY, LAST, SUMMARY, Layout
from plad.learn import distributed as dist
from plad.learn.curriculum import Curriculum, CurriculumConfig
from plad.learn.diagnostics import prefix_gap
from plad.learn.loop import budget_seconds
from plad.learn.synthetic import load_programs, make_batch
from plad.learn.train import TrainConfig, fit
from plad.model.checkpoint import read_checkpoint
from plad.model.network import Architecture, ModelConfig, PLADNet, count_parameters


@dataclass
class PretrainConfig:
    domain: str = field(kw_only=True)
    #: "auto" (CUDA when present), "cpu" or "cuda"
    device: str = "auto"
    #: torch CPU threads (None: torch's default)
    threads: int | None = None
    seed: int = 0
    #: synthetic validation shapes decoded greedily each epoch for the domain metric
    val_metric_shapes: int = 200
    #: validation programs of the prefix-swap gap (plad.learn.diagnostics), the first ones of the split
    gap_programs: int = 128
    #: real validation shapes decoded greedily each epoch (evenly spaced over the split; 0: none)
    real_val_shapes: int = 0
    #: budget of training time, minutes, counted across resumes (None: none)
    max_minutes: float | None = None
    model: Architecture = field(default_factory=Architecture)
    train: TrainConfig = field(default_factory=TrainConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)



def complexities(domain, data: dict[str, torch.Tensor], path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(train, val) program complexities: from the synthetic file, or computed for a file written before it
    recorded them."""
    if domain.complexity_kind is None:
        raise ConfigError(f"{path}: curriculum.enabled, but domain {domain.name} defines no program complexity")
    return tuple(data[f"{s}_complexity"].numpy() if f"{s}_complexity" in data
                 else domain.complexity(data[s].numpy()) for s in ("train", "val"))



def real_val_shapes(path: Path, n: int) -> torch.Tensor:
    """``n`` real validation shapes, evenly spaced over the prepared split (which is ordered, e.g. by category)."""
    from plad.data.files import load_split

    if not path.exists():
        raise ConfigError(f"{path}: prepared real shapes not found (real_val_shapes: {n}); run the prepare stage "
                          f"first or set real_val_shapes: 0")
    return torch.from_numpy(load_split(path, "val", n)[0])



def pretrain(cfg: PretrainConfig, layout: Layout = Layout(), on_epoch=None) -> dict:
    """Train p(z|x) on the domain's synthetic programs; returns the summary (also written to disk)."""
    from plad.domains import get_domain
    from plad.model.decode import greedy_decode

    domain = get_domain(cfg.domain)
    dist.init()   # under torchrun: join the other ranks (before the model goes to this rank's GPU)
    device = resolve_device(cfg.device)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    data = load_programs(layout.synthetic(cfg.domain))
    train, val = data["train"], data["val"]
    curriculum = Curriculum(cfg.curriculum, *complexities(domain, data, layout.synthetic(cfg.domain))) \
        if cfg.curriculum.enabled else None
    real = real_val_shapes(layout.prepared(cfg.domain), cfg.real_val_shapes).to(device) \
        if cfg.real_val_shapes else None
    model = PLADNet(ModelConfig.for_domain(cfg.model, domain)).to(device)
    out = layout.pretrain_dir(cfg.domain)
    out.mkdir(parents=True, exist_ok=True)
    history = out / HISTORY
    bs = cfg.train.batch_size

    program_lengths = (train >= 0).sum(1).numpy()

    def indices(epoch: int) -> Iterator[np.ndarray]:
        # a stream fixed by (seed, epoch): a resumed run trains on the same batches; ranks take turns
        if curriculum is not None:   # the stage's mix with replay; every rank draws its own part
            yield from curriculum.indices(epoch, cfg.seed, bs)
            return
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch)
        while True:
            perm = torch.randperm(len(train), generator=gen)
            for start in dist.chunk_starts(len(perm), bs):
                yield perm[start:start + bs].numpy()

    def batches(epoch: int) -> Iterator[tuple[torch.Tensor, ...]]:
        # grouped by program length, bucket_pool of this rank's batches at a time (plad.data.batching)
        rng = np.random.default_rng([cfg.seed, epoch, dist.rank()])
        for idx in bucketed(indices(epoch), program_lengths, cfg.train.bucket_pool, rng):
            yield make_batch(domain, train[torch.from_numpy(idx)], device)

    val_batches = [make_batch(domain, val[i:i + bs], device) for i in range(0, len(val), bs)]
    gap_batch = make_batch(domain, val[: max(2, cfg.gap_programs)], device)   # fixed: comparable across epochs
    metric = domain.metric

    def val_loss(m: PLADNet, batches) -> tuple[float, float]:
        """Token-weighted mean loss and accuracy over batches."""
        tot, acc, n = 0.0, 0.0, 0
        for shapes, programs, lengths in batches:
            loss, a = m.loss(shapes, programs, lengths)
            k = int(lengths.sum())
            tot, acc, n = tot + float(loss) * k, acc + float(a) * k, n + k
        return tot / n, acc / n

    def greedy_metric(m: PLADNet, shapes: torch.Tensor) -> float:
        decoded = greedy_decode(m, domain.tokens, shapes)
        return float(metric(domain.execute(pad_programs(decoded, device=device)), shapes).mean())

    @torch.no_grad()
    def validate(m: PLADNet) -> dict[str, float]:
        m.eval()
        loss, acc = val_loss(m, val_batches)
        shapes = torch.cat([b[0] for b in val_batches])[: cfg.val_metric_shapes]
        out = {"val_loss": loss, "val_acc": acc, f"val_{metric.name}": greedy_metric(m, shapes),
               "prefix_gap": prefix_gap(m, *gap_batch)}
        if real is not None:
            out[f"real_val_{metric.name}"] = greedy_metric(m, real)
        if curriculum is not None:   # the stage's own validation programs (the final stage's: all)
            rows = val[torch.from_numpy(curriculum.val_mask())]
            out["stage_val_loss"], out["stage_val_acc"] = (loss, acc) if curriculum.final else val_loss(
                m, [make_batch(domain, rows[i:i + bs], device) for i in range(0, len(rows), bs)])
            out["stage_prefix_gap"] = out["prefix_gap"] if curriculum.final or len(rows) < 2 else \
                prefix_gap(m, *make_batch(domain, rows[: max(2, cfg.gap_programs)], device))
        return out

    def record(unit: int, row: dict[str, float]) -> None:
        # history.csv keeps its columns (DVC plots it: x epoch, y val_loss); the loop's own
        # bookkeeping (unit, val, seconds) is in last.pt
        metrics = {k: v for k, v in row.items() if k not in ("unit", "val", "seconds", "unit_seconds")}
        metrics["epoch_seconds"] = row["unit_seconds"]
        line = {"epoch": unit, **{k: round(v, 6) for k, v in metrics.items()}}
        new = not history.exists()
        with history.open("a", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(line))
            if new:
                writer.writeheader()
            writer.writerow(line)
        if on_epoch:
            on_epoch(unit, metrics)

    # settings that make a checkpoint incompatible (budgets and epoch caps may change on resume)
    fingerprint = {"model": model.cfg.to_dict(), "seed": cfg.seed, "batch_size": bs, "lr": cfg.train.lr,
                   "steps_per_epoch": cfg.train.steps_per_epoch, "train_programs": len(train),
                   "synthetic_checksum": int(train[:1000].sum()) + int(val.sum()),
                   "warmup_steps": cfg.train.warmup_steps, "curriculum": asdict(cfg.curriculum),
                   # buckets change the batches (plain batches keep the fingerprint of earlier versions)
                   **({"bucket_pool": cfg.train.bucket_pool} if cfg.train.bucket_pool > 1 else {})}
    last = out / LAST
    if dist.is_main() and (not last.exists() or read_checkpoint(last).get("fingerprint") != fingerprint):
        history.unlink(missing_ok=True)  # a fresh run: no stale epochs in the history
    start = time.monotonic()
    result = fit(model, batches, validate, cfg.train, out, domain=cfg.domain, token_names=domain.tokens.names,
                 budget_seconds=budget_seconds(cfg.max_minutes), on_unit=record, desc=f"pretrain {cfg.domain}",
                 fingerprint=fingerprint, stages=curriculum)
    final = validate(model)
    summary = {"domain": cfg.domain, "parameters": count_parameters(model), **result.summary(),
               "wall_seconds_this_call": round(time.monotonic() - start, 1), "train_programs": len(train),
               **{k: round(v, 6) for k, v in final.items()}}
    if dist.is_main():
        atomic_write_text(out / SUMMARY, json.dumps(summary, indent=2) + "\n")
    return summary
