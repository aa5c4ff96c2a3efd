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
import itertools
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from plad.config import ConfigError
from plad.data.batching import bucketed
from plad.device import Precision, check_precision, resolve_device, resolve_precision
from plad.domains.base import Domain, pad_programs
from plad.fsutil import atomic_write_text, sha256_file
from plad.layout import BEST, HISTORY, LAST, PROVENANCE, SUMMARY, Layout
from plad.learn import distributed as dist
from plad.learn.curriculum import Curriculum, CurriculumConfig
from plad.learn.diagnostics import prefix_gap
from plad.learn.loop import budget_seconds
from plad.learn.state import totals
from plad.learn.synthetic import ExecutorPool, load_programs, make_batch
from plad.learn.train import VAL_LOSS, FitSetup, Init, TrainConfig, fit
from plad.model.checkpoint import MAX_PARAMETERS, estimate_parameters, read_checkpoint
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
    #: arithmetic of the training forward passes (:mod:`plad.device`): "fp32", "bf16" (autocast) or "auto"
    #: (bf16 on a CUDA GPU that computes it natively, else fp32: a CPU run is unchanged)
    precision: str = "fp32"
    #: compile the encoder with torch.compile: the part of a training step whose input shape is fixed by the
    #: batch size (the decoder's length changes from batch to batch). It did not help on our CPUs
    #: (docs/gpu.md); ``python -m bench.gpu_check --compile`` measures it on a GPU
    compile: bool = False
    #: worker processes that execute the next batches' synthetic programs on the CPU while the model trains
    #: (:class:`plad.learn.synthetic.ExecutorPool`); 0: executed in the training process, on its device (CSG's
    #: executors run on a GPU, ShapeAssembly's runs in Python on the CPU)
    loader_workers: int = 0
    model: Architecture = field(default_factory=Architecture)
    train: TrainConfig = field(default_factory=TrainConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    #: continue from a checkpoint: None (from scratch); "shipped" (the domain's shipped pretrained network,
    #: resolved by the stage: :func:`plad.shipped.pretrained_checkpoint`); or the path of a pretraining's
    #: ``last.pt`` or of a shipped ``pretrained.pt``, relative to the layout root. The run goes on from its
    #: weights, optimizer, schedule, curriculum stage and history as a new segment, in which
    #: ``train.max_epochs`` and ``max_minutes`` count this segment's epochs and minutes
    init: str | None = None
    #: the learning rate of a continued run: "restart" (back to ``train.lr`` after the warm-up, a fresh plateau
    #: schedule, Adam's moments kept: a rate that a plateau rule drove to its floor is never resumed) or
    #: "resume" (the saved schedule goes on: the segment trains as the run would have gone on)
    continue_lr: str = "restart"

    def __post_init__(self) -> None:
        check_precision(self.precision)


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


CONTINUE_LR = ("restart", "resume")


def check_epochs(cfg: PretrainConfig, init_path: Path | None) -> None:
    """``train.max_epochs: 0`` only for a pretraining that continues a checkpoint (it takes that one over); a
    fresh one of no epochs would train nothing and leave no history (ConfigError, one line)."""
    if cfg.train.max_epochs == 0 and init_path is None and cfg.init is None:
        raise ConfigError(f"pretrain.{cfg.domain}.train.max_epochs = 0 trains nothing: only a pretraining that "
                          f"continues a checkpoint (init) may take 0 epochs")


def read_init(path: Path, cfg: PretrainConfig, model_cfg: ModelConfig) -> dict:
    """The training state a continued pretraining starts from, checked against this run's settings."""
    from plad.learn.state import check_training_state
    from plad.model.checkpoint import CheckpointError

    if not path.is_file():
        raise ConfigError(f"pretrain.{cfg.domain}.init: {path} not found (a pretraining's last.pt or a shipped "
                          f"pretrained.pt; null: from scratch)")
    try:
        payload = read_checkpoint(path)
    except CheckpointError as err:
        raise ConfigError(f"pretrain.{cfg.domain}.init: {err}") from None
    if payload.get("domain") != cfg.domain:
        raise ConfigError(f"pretrain.{cfg.domain}.init: {path} is a {payload.get('domain')} checkpoint")
    missing = [k for k in ("optimizer", "scheduler", "rng") if k not in payload]
    if missing or not ("loop" in payload or "train_state" in payload):
        what = ", ".join(missing) or "loop"
        raise ConfigError(f"pretrain.{cfg.domain}.init: {path} holds no training state to continue ({what} "
                          "missing): a pretraining's last.pt or a shipped pretrained.pt")
    theirs, ours = payload.get("config", {}), model_cfg.to_dict()
    differ = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
    if differ:
        raise ConfigError(f"pretrain.{cfg.domain}.init: {path} is another network than pretrain.{cfg.domain}.model "
                          f"({', '.join(f'{k}: {theirs.get(k)!r} there, {ours.get(k)!r} here' for k in differ)})")
    if (payload.get("stages") is not None) != cfg.curriculum.enabled:
        raise ConfigError(f"pretrain.{cfg.domain}.init: {path} was trained with curriculum.enabled "
                          f"{not cfg.curriculum.enabled}; continue it with the same setting")
    try:   # the one check of a training state before training continues from it (weights, Adam, RNGs, ...)
        check_training_state(path, payload)
    except CheckpointError as err:
        raise ConfigError(f"pretrain.{cfg.domain}.init: {err}") from None
    return payload


def legacy_segment(payload: dict) -> dict:
    """The one segment of a checkpoint written before segments were recorded, from its loop state: what it
    says for sure (epochs, steps, shapes, seconds, the last epoch's metrics); commit and threads unknown."""
    from plad.learn.loop import LoopState, upgrade_state

    state = LoopState.from_dict(payload["loop"] if "loop" in payload else upgrade_state(payload["train_state"],
                                                                                       "epoch"), "epoch")
    fp = payload.get("fingerprint") or {}
    steps = state.unit * int(fp.get("steps_per_epoch", 0))
    return {"recorded": False, "commit": None, "dirty": None, "threads": None, "device": None,
            "epochs": [1, state.unit], "steps": steps, "shapes_seen": steps * int(fp.get("batch_size", 0)),
            "train_seconds": round(state.seconds, 1), "cpu_hours": None,
            "synthetic": {"train_programs": fp.get("train_programs"), "checksum": fp.get("synthetic_checksum")},
            "end": _end_metrics(state.history)}


def _end_metrics(history: list[dict]) -> dict:
    last = history[-1] if history else {}
    return {k: round(float(v), 6) for k, v in last.items()
            if k.startswith(("real_val_", "val_")) or k in ("prefix_gap", "train_loss", "lr")}


@dataclass
class _Run:
    """One call of :func:`pretrain`: what its phases share, as :func:`_set_up` made it."""

    cfg: PretrainConfig
    layout: Layout
    domain: Domain
    device: torch.device
    train: torch.Tensor
    val: torch.Tensor
    curriculum: Curriculum | None
    real: torch.Tensor | None
    model: PLADNet
    init_path: Path | None
    init_payload: dict | None
    precision: Precision
    out: Path
    bs: int   # cfg.train.batch_size
    history: Path   # out / history.csv
    last: Path   # out / last.pt


def pretrain(cfg: PretrainConfig, layout: Layout = Layout(), on_epoch=None, init_path: Path | None = None) -> dict:
    """Train p(z|x) on the domain's synthetic programs; returns the summary (also written to disk).

    ``init_path``: the checkpoint ``cfg.init`` names, resolved by the caller (the stage resolves
    ``"shipped"``); by default ``cfg.init`` relative to the layout root.
    """
    run = _set_up(cfg, layout, _resolve_init(cfg, layout, init_path))
    loader = _Loader(run)
    validate = _validator(run)
    record = _recorder(run.history, on_epoch)
    fingerprint = _fingerprint(run)
    if dist.is_main():
        _rewrite_history(run, fingerprint, record)
    prior, provenance = _provenance(run, fingerprint)
    start = time.monotonic()
    init = Init(run.init_payload, VAL_LOSS, cfg.continue_lr == "restart", cfg.train.lr) if run.init_payload else None
    loader.pool = ExecutorPool(run.domain.name, cfg.loader_workers) if cfg.loader_workers else None
    try:
        setup = FitSetup(cfg.domain, run.domain.tokens.names, budget_seconds=budget_seconds(cfg.max_minutes),
                         on_unit=record, desc=f"pretrain {cfg.domain}", fingerprint=fingerprint,
                         stages=run.curriculum, init=init, extra=provenance, precision=run.precision)
        result = fit(run.model, loader, validate, cfg.train, run.out, setup)
    finally:
        if loader.pool is not None:
            loader.pool.close()
    final = validate(run.model)
    if run.last.exists():
        record_ = provenance(read_checkpoint(run.last)["loop"])["provenance"]
    else:   # a segment of no epochs: the model is the one continued, and so is its record
        record_ = {"segments": prior, "totals": totals(prior)} if prior else None
    summary = {"domain": cfg.domain, "parameters": count_parameters(run.model), **result.summary(),
               "wall_seconds_this_call": round(time.monotonic() - start, 1), "train_programs": len(run.train),
               **{k: round(v, 6) for k, v in final.items()},
               **({"totals": record_["totals"]} if record_ else {})}
    if dist.is_main():
        _write_outputs(run, fingerprint, record_, summary)
    return summary


def _resolve_init(cfg: PretrainConfig, layout: Layout, init_path: Path | None) -> Path | None:
    """The checkpoint a continued pretraining starts from (None: from scratch), after the checks of the
    settings that say so."""
    if cfg.continue_lr not in CONTINUE_LR:
        raise ConfigError(f"pretrain.{cfg.domain}.continue_lr: {cfg.continue_lr!r}; one of {', '.join(CONTINUE_LR)}")
    check_epochs(cfg, init_path)
    if init_path is None and cfg.init is not None:
        if cfg.init == "shipped":
            raise ConfigError(f"pretrain.{cfg.domain}.init: 'shipped' is resolved by the pretrain stage "
                              "(plad.stages.pretrain); pass init_path")
        init_path = Path(cfg.init) if Path(cfg.init).is_absolute() else layout.root / cfg.init
    return init_path


def _set_up(cfg: PretrainConfig, layout: Layout, init_path: Path | None) -> _Run:
    """The device, the programs, the curriculum, the network (and the state it continues), the output folder."""
    from plad.domains import get_domain

    domain = get_domain(cfg.domain)
    dist.init()   # under torchrun: join the other ranks (before the model goes to this rank's GPU)
    device = resolve_device(cfg.device)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    data = load_programs(layout.synthetic(cfg.domain))
    curriculum = Curriculum(cfg.curriculum, *complexities(domain, data, layout.synthetic(cfg.domain))) \
        if cfg.curriculum.enabled else None
    real = real_val_shapes(layout.prepared(cfg.domain), cfg.real_val_shapes).to(device) \
        if cfg.real_val_shapes else None
    model_cfg = ModelConfig.for_domain(cfg.model, domain)
    if estimate_parameters(model_cfg) > MAX_PARAMETERS:   # refused before anything is allocated
        raise ConfigError(f"pretrain.{cfg.domain}.model declares a network of about "
                          f"{estimate_parameters(model_cfg):,} parameters, more than the limit of {MAX_PARAMETERS:,}")
    model = PLADNet(model_cfg).to(device)
    init_payload = read_init(init_path, cfg, model.cfg) if init_path is not None else None
    precision = resolve_precision(cfg.precision, device)
    if cfg.compile:
        model.encoder.compile()   # in place: the state dict keeps its keys
    out = layout.pretrain_dir(cfg.domain)
    out.mkdir(parents=True, exist_ok=True)
    return _Run(cfg, layout, domain, device, data["train"], data["val"], curriculum, real, model, init_path,
                init_payload, precision, out, cfg.train.batch_size, out / HISTORY, out / LAST)


class _Loader:
    """``loader(epoch)``: the epoch's training batches, on the run's device; ``pool``, when set (just before
    training), executes them in worker processes."""

    def __init__(self, run: _Run):
        self.run = run
        self.pool: ExecutorPool | None = None
        self.program_lengths = (run.train >= 0).sum(1).numpy()

    def indices(self, epoch: int) -> Iterator[np.ndarray]:
        # a stream fixed by (seed, epoch): a resumed run trains on the same batches; ranks take turns
        cfg, bs = self.run.cfg, self.run.bs
        if self.run.curriculum is not None:   # the stage's mix with replay; every rank draws its own part
            yield from self.run.curriculum.indices(epoch, cfg.seed, bs)
            return
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch)
        while True:
            perm = torch.randperm(len(self.run.train), generator=gen)
            for start in dist.chunk_starts(len(perm), bs):
                yield perm[start:start + bs].numpy()

    def __call__(self, epoch: int) -> Iterator[tuple[torch.Tensor, ...]]:
        # grouped by program length, bucket_pool of this rank's batches at a time (plad.data.batching); the
        # epoch's steps exactly, so that workers execute no batch that is not trained on
        cfg, train = self.run.cfg, self.run.train
        rng = np.random.default_rng([cfg.seed, epoch, dist.rank()])
        rows = (train[torch.from_numpy(idx)] for idx in
                itertools.islice(bucketed(self.indices(epoch), self.program_lengths, cfg.train.bucket_pool, rng),
                                 cfg.train.steps_per_epoch))
        if self.pool is not None:
            yield from self.pool.batches(rows, self.run.device)
        else:
            for r in rows:
                yield make_batch(self.run.domain, r, self.run.device)


def _validator(run: _Run) -> Callable[[PLADNet], dict[str, float]]:
    """The epoch's validation: loss and accuracy on the synthetic validation programs, the greedy metric, the
    prefix gap, and (when set) the real shapes' metric and the curriculum stage's own validation."""
    from plad.model.decode import greedy_decode

    cfg, domain, device, val, bs, curriculum = run.cfg, run.domain, run.device, run.val, run.bs, run.curriculum
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
        if run.real is not None:
            out[f"real_val_{metric.name}"] = greedy_metric(m, run.real)
        if curriculum is not None:   # the stage's own validation programs (the final stage's: all)
            rows = val[torch.from_numpy(curriculum.val_mask())]
            out["stage_val_loss"], out["stage_val_acc"] = (loss, acc) if curriculum.final else val_loss(
                m, [make_batch(domain, rows[i:i + bs], device) for i in range(0, len(rows), bs)])
            out["stage_prefix_gap"] = out["prefix_gap"] if curriculum.final or len(rows) < 2 else \
                prefix_gap(m, *make_batch(domain, rows[: max(2, cfg.gap_programs)], device))
        return out

    return validate


def _recorder(history: Path, on_epoch) -> Callable[..., None]:
    """``record(unit, row, notify=True)``: appends the epoch's row to ``history.csv`` and tells ``on_epoch``."""

    def record(unit: int, row: dict[str, float], notify: bool = True) -> None:
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
        if on_epoch and notify:
            on_epoch(unit, metrics)

    return record


def _fingerprint(run: _Run) -> dict:
    """The settings that make a checkpoint incompatible (budgets and epoch caps may change on resume)."""
    cfg, train, init_path = run.cfg, run.train, run.init_path
    return {"model": run.model.cfg.to_dict(), "seed": cfg.seed, "batch_size": run.bs, "lr": cfg.train.lr,
            "steps_per_epoch": cfg.train.steps_per_epoch, "train_programs": len(train),
            "synthetic_checksum": int(train[:1000].sum()) + int(run.val.sum()),
            "warmup_steps": cfg.train.warmup_steps, "curriculum": asdict(cfg.curriculum),
            # buckets change the batches (plain batches keep the fingerprint of earlier versions)
            **({"bucket_pool": cfg.train.bucket_pool} if cfg.train.bucket_pool > 1 else {}),
            # a near-miss loss changes the steps (the plain loss keeps the fingerprint of earlier versions)
            **({"near_smoothing": cfg.train.near_smoothing} if cfg.train.near_smoothing else {}),
            # a continued run resumes only from a last.pt that continued the same checkpoint the same way
            **({"init": sha256_file(init_path), "continue_lr": cfg.continue_lr} if init_path else {})}


def _rewrite_history(run: _Run, fingerprint: dict, record: Callable[..., None]) -> None:
    """history.csv is written again from the state the run starts from, never appended to as found: DVC
    deletes it before running the stage (a plot, not persisted) while last.pt persists, and a kill between
    last.pt's commit and the row's append leaves it a row short. The state: the last.pt a run resumes,
    else the checkpoint a new segment continues (its epochs come first), else none (a fresh run)."""
    from plad.learn.loop import LoopState

    saved = read_checkpoint(run.last) if run.last.exists() else None
    state = saved if saved is not None and saved.get("fingerprint") == fingerprint else run.init_payload
    run.history.unlink(missing_ok=True)
    if state is not None:
        for row in LoopState.from_dict(state.get("loop") or state["train_state"], "epoch").history:
            if row.get("unit", 0) > 0:
                record(row["unit"], row, notify=False)


def _provenance(run: _Run, fingerprint: dict) -> tuple[list[dict], Callable[[dict], dict]]:
    """The segments of the checkpoint continued, and ``provenance(loop_state)``: the ``last.pt`` keys that
    record them and this one (rebuilt from the loop state at every commit of last.pt, so that a killed run's
    checkpoint says what it holds)."""
    from datetime import datetime, timezone

    from plad.learn.loop import LoopState
    from plad.provenance import code_state, machine

    cfg, init_path, init_payload, device = run.cfg, run.init_path, run.init_payload, run.device
    prior = ((init_payload.get("provenance") or {}).get("segments") or [legacy_segment(init_payload)]) \
        if init_payload is not None else []
    here = {"recorded": True, **code_state(), "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "device": str(device), "threads": torch.get_num_threads(), "world": dist.world(), "machine": machine(),
            "init": {"file": init_path.name, "sha256": sha256_file(init_path)} if init_path else None,
            "continue_lr": cfg.continue_lr if init_path else None,
            "synthetic": synthetic_record(run.layout, cfg.domain, len(run.train), fingerprint["synthetic_checksum"]),
            # a path `init` is this machine's: the segment names the checkpoint by `init` (file name, sha256)
            "params": {**asdict(cfg), **({"init": init_path.name} if init_path and cfg.init != "shipped" else {})}}

    def provenance(state: dict) -> dict:
        s = LoopState.from_dict(state, "epoch")
        steps = (s.unit - s.segment_unit) * cfg.train.steps_per_epoch
        seconds = s.seconds - s.segment_seconds
        hours = seconds * (dist.world() if device.type == "cuda" else here["threads"]) / 3600
        segment = {**here, "epochs": [s.segment_unit + 1, s.unit], "steps": steps,
                   "shapes_seen": steps * run.bs * dist.world(), "train_seconds": round(seconds, 1),
                   "cpu_hours": round(hours, 4) if device.type == "cpu" else None,
                   "gpu_hours": round(hours, 4) if device.type == "cuda" else None,
                   "end": _end_metrics(s.history if s.unit > s.segment_unit else [])}
        segments = [*prior, segment]
        return {"provenance": {"segments": segments, "totals": totals(segments)}}

    return prior, provenance


def _write_outputs(run: _Run, fingerprint: dict, record_: dict | None, summary: dict) -> None:
    """Rank 0's files after training: ``last.pt`` of a segment of no epochs, the provenance in ``best.pt`` and
    ``provenance.json``, ``summary.json``."""
    from plad.learn.loop import LoopState, upgrade_state
    from plad.model.checkpoint import save_checkpoint

    cfg, out, model, names, init_payload = run.cfg, run.out, run.model, run.domain.tokens.names, run.init_payload
    if not run.last.exists() and init_payload is not None:
        # a segment of no epochs still leaves a state to continue or ship: the one it continued, now with
        # its record and this run's fingerprint (so that running it again changes nothing)
        state = init_payload.get("loop") or upgrade_state(init_payload["train_state"], "epoch")
        keep = {k: v for k, v in init_payload.items()
                if k not in ("format", "domain", "tokens", "config", "state_dict", "loop", "train_state")}
        save_checkpoint(run.last, model, cfg.domain, names,
                        {**keep, "loop": LoopState.from_dict(state, "epoch").new_segment(VAL_LOSS).to_dict(),
                         "fingerprint": fingerprint, **({"provenance": record_} if record_ else {})})
    if record_ is not None:   # the selected model says what it holds too
        best = read_checkpoint(out / BEST)
        save_checkpoint(out / BEST, model, cfg.domain, names,
                        {k: best[k] for k in ("unit", "val") if k in best} | {"provenance": record_})
        atomic_write_text(out / PROVENANCE, json.dumps(record_, indent=2) + "\n")
    atomic_write_text(out / SUMMARY, json.dumps(summary, indent=2) + "\n")


def synthetic_record(layout: Layout, domain: str, train_programs: int, checksum: int) -> dict:
    """What the segment trained on: the synthetic file's sampler and seed (from its summary) and size."""
    info = {}
    path = layout.synthetic_summary(domain)
    if path.is_file():
        try:
            info = json.loads(path.read_text())
        except ValueError:
            info = {}
    return {"file": layout.synthetic(domain).name, "sampler": info.get("sampler"), "seed": info.get("seed"),
            "train_programs": train_programs, "checksum": checksum}


