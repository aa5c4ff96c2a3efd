"""Networks taught by search: supervised training of p(z|x) on search labels of the real shapes (issue 58).

Beyond the paper, beside its rows: with the labels of :mod:`plad.learn.labels` fixed, teaching is plain
maximum likelihood (:func:`plad.learn.train.fit`) on batches drawn, each whole from one source by weight,
from

* ``st``:   (real training shape, its label): the real distribution, with the search's approximation;
* ``lest``: (the label's execution, the label): exact pairs on the shapes search draws;
* ``aug``:  (execution, program) of a label changed by an exact symmetry of its grammar and an edit
  (:mod:`plad.learn.augment`), drawn afresh every batch: an unlimited stream near the real distribution.

Every epoch measures the fit beside validation: the metric at beam ``fit_beam`` (greedy by default) and
at beam ``fit_beam_wide`` on a fixed, evenly spaced sample of the labelled training shapes (``fit`` and
``fit_wide``), and the validation metric at beam ``val_beam`` on the validation shapes (``val``, which
selects the model). ``history.csv`` holds one row per epoch; the summary gives the labels' own metric on
the fit sample, the ceiling the fit is measured against.

Writes to ``runs/finetune/<domain>/taught/`` (:mod:`plad.layout`): ``best.pt`` (selected on ``val``),
``last.pt`` (resume state: a killed run continues after its last finished epoch), ``history.csv`` and
``summary.json`` (also ``results/finetune/<domain>/taught.json``). The evaluate stage evaluates it as the
method ``taught``.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import random
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from plad.config import ConfigError
from plad.fsutil import atomic_write_text
from plad.layout import BEST, LAST, SUMMARY, Layout
from plad.learn.train import TrainConfig, resumes

#: the method key of a taught network (its run folder and its evaluation)
TAUGHT = "taught"
HISTORY_FILE = "history.csv"
#: the batch sources of teaching
TEACH_SOURCES = ("st", "lest", "aug")


@dataclass
class AugmentConfig:
    """How the ``aug`` source changes a label (:func:`plad.learn.augment.pairs`)."""

    #: chance of one random exact symmetry of the grammar (the identity among them)
    symmetry_share: float = 0.5
    #: chance of one random edit (parameter jitter, dropping a part, grafting a sub-program of another label)
    edit_share: float = 0.5


@dataclass
class GrowConfig:
    """Larger sizes for the starting network (:func:`plad.model.grow.grow`: the same function, more capacity);
    null: the start's own size."""

    enc_channels: list[int] | None = None
    n_layers: int | None = None
    dim_ff: int | None = None

    def asked(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass
class ThenConfig:
    """A second teaching segment (issue 58): once the first has ended, its best network grown again and taught
    on the same labels with the schedule restarted (the rate, its halvings and the patience as ``train`` gives
    them), ``max_epochs`` more epochs. The first segment keeps its folder, ``taught/first/``; the second is
    the stage's network, ``taught/best.pt``."""

    grow: GrowConfig = field(default_factory=GrowConfig)
    max_epochs: int = 10


@dataclass
class TeachConfig:
    """Params ``teach.<domain>`` (stage ``teach@<domain>``)."""

    domain: str = field(kw_only=True)
    #: where training starts: "pretrained" (the domain's shipped SP network), "search_seeded" (the domain's
    #: search-seeded LEST+ST+WS network, kept as ``plad/shipped/<domain>/search_seeded.pt``), "taught" (a taught
    #: network kept as it was shipped, ``plad/shipped/<domain>/taught.pt``: a run that continues it) or the path
    #: of a checkpoint. Never the shipped model: shipping this stage's own network would change its start
    init: str = "pretrained"
    device: str = "auto"
    #: arithmetic of the training forward passes (:mod:`plad.device`); decoding stays float32
    precision: str = "fp32"
    threads: int | None = 1
    seed: int = 0
    #: only the first N labels of the labelling order (a uniform sample of the split; null: all)
    label_limit: int | None = None
    #: validation shapes, evenly spaced over the split (null: all), and the beam that selects the model
    val_limit: int | None = 150
    val_beam: int = 3
    #: the fit: this many labelled training shapes, evenly spaced over the labels, at two beams every epoch
    fit_shapes: int = 100
    fit_beam: int = 1
    fit_beam_wide: int = 10
    infer_batch: int = 100
    #: weights of the batch sources (st, lest, aug); a source of weight 0 is left out
    sources: dict[str, float] = field(default_factory=lambda: {"st": 1.0, "lest": 1.0, "aug": 0.0})
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    #: grow the starting network before teaching (issue 58: the network's size at equal steps from the same start)
    grow: GrowConfig = field(default_factory=GrowConfig)
    #: wall-clock safety net in minutes (null: none), for each segment: the epochs fix the work
    max_minutes: float | None = None
    train: TrainConfig = field(default_factory=TrainConfig)
    #: a second segment from the first's best network (null: none)
    then: ThenConfig | None = None

    def __post_init__(self) -> None:
        from plad.device import check_precision

        check_precision(self.precision)


def check(cfg: TeachConfig, where: str) -> None:
    """Fail early (ConfigError naming ``where``) on a bad configuration."""
    unknown = sorted(set(cfg.sources) - set(TEACH_SOURCES))
    if unknown:
        raise ConfigError(f"{where}.sources: unknown source(s) {', '.join(unknown)}; sources are "
                          f"{', '.join(TEACH_SOURCES)}")
    if any(not (w >= 0 and math.isfinite(w)) for w in cfg.sources.values()) or not sum(cfg.sources.values()) > 0:
        raise ConfigError(f"{where}.sources: weights must be finite, at least 0, and not all 0 ({cfg.sources})")
    for name in ("symmetry_share", "edit_share"):
        v = getattr(cfg.augment, name)
        if not 0.0 <= v <= 1.0:
            raise ConfigError(f"{where}.augment.{name} = {v}: expected a share between 0 and 1")
    for name in ("val_beam", "fit_beam", "fit_beam_wide", "infer_batch"):
        if getattr(cfg, name) < 1:
            raise ConfigError(f"{where}.{name} = {getattr(cfg, name)}: expected at least 1")
    if cfg.fit_shapes < 0:
        raise ConfigError(f"{where}.fit_shapes = {cfg.fit_shapes}: expected at least 0")
    for name in ("label_limit", "val_limit"):
        v = getattr(cfg, name)
        if v is not None and v < 1:
            raise ConfigError(f"{where}.{name} = {v}: expected a positive number of shapes, or null")


Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _batch(shapes: np.ndarray, programs: np.ndarray, device: torch.device) -> Batch:
    """(shapes (N, *s) float, programs (N, L) long, lengths (N,)) from bool shapes and -1 padded programs."""
    from plad.device import to_device
    from plad.domains.base import split_padding

    tokens, lengths = split_padding(torch.from_numpy(programs.astype(np.int64)))
    return to_device(shapes, device), to_device(tokens, device), to_device(lengths, device)


def label_sources(domain, real: np.ndarray, programs: np.ndarray, executions: np.ndarray, cfg: TeachConfig,
                  device: torch.device) -> dict:
    """The batch sources (``(rng, n) -> Batch``) of the configured weights: real shapes (N, *s) with their
    labels (N, L) -1 padded, and the labels' executions (N, *s)."""
    def st(rng: np.random.Generator, n: int) -> Batch:
        idx = rng.integers(len(programs), size=n)
        return _batch(real[idx], programs[idx], device)

    def lest(rng: np.random.Generator, n: int) -> Batch:
        idx = rng.integers(len(programs), size=n)
        return _batch(executions[idx], programs[idx], device)

    lists = [row[row >= 0].tolist() for row in programs]

    def aug(rng: np.random.Generator, n: int) -> Batch:
        from plad.learn.augment import pairs
        from plad.rewrite.pool import pad_programs

        idx = rng.integers(len(lists), size=n)
        shapes, changed = pairs(domain, [lists[i] for i in idx], rng, symmetry_share=cfg.augment.symmetry_share,
                                edit_share=cfg.augment.edit_share)
        return _batch(np.asarray(shapes, dtype=bool), pad_programs(changed, programs.shape[1]), device)

    every = {"st": st, "lest": lest, "aug": aug}
    return {k: every[k] for k, w in cfg.sources.items() if w > 0}


def _write_history(path: Path, rows: list[dict]) -> None:
    keys: list[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keys)
    writer.writeheader()
    for r in rows:
        writer.writerow({k: r.get(k, "") for k in keys})
    atomic_write_text(path, buf.getvalue())


def _fingerprint(cfg: TeachConfig, labels_sha256: str, init_digest: str, n: int) -> dict:
    """What identifies a teaching run's work, so that a last.pt of other work is not resumed (fit starts over):
    the labels, the start (its network's digest: not the name ``init`` gave it), how many labels, the config but
    for its safety net, device, threads and epochs."""
    fingerprint = {"labels": labels_sha256, "init": init_digest, "n": n,
                   "config": {k: v for k, v in asdict(cfg).items()
                              if k not in ("max_minutes", "device", "threads", "init")}}
    # the plain loss (near_smoothing 0) keeps the fingerprint of the runs before the key existed
    fingerprint["config"]["train"] = {k: v for k, v in asdict(cfg.train).items()
                                      if k != "max_epochs" and not (k == "near_smoothing" and not v)}
    # likewise a start that is not grown; a segment's work is its own (a first segment's is the same work
    # whether or not a second follows it)
    if not cfg.grow.asked():
        fingerprint["config"].pop("grow")
    fingerprint["config"].pop("then")
    return fingerprint


def _history(path: Path, last: Path, fingerprint: dict) -> list[dict]:
    """The rows of ``path`` when the run continues ``last`` (the same work), else none: they are other work's."""
    if not (path.exists() and resumes(last, fingerprint)):
        return []
    with open(path, newline="") as fh:
        return [dict(r) for r in csv.DictReader(fh)]


#: the first segment's folder inside the run folder, where a second segment follows it (``then``)
FIRST = "first"
#: the files of a segment's folder (what moves when a finished run becomes the first of two segments)
SEGMENT_FILES = (LAST, BEST, HISTORY_FILE, SUMMARY)


def teach(cfg: TeachConfig, start: Path, layout: Layout = Layout(), log=print) -> dict:
    """Teach one domain's network, from the checkpoint ``start`` (what ``cfg.init`` names), on its search labels;
    returns the summary (a pure function of the config and the files it names: labels, prepared shapes, start).

    With ``cfg.then``, two segments: the first (``cfg`` without ``then``) in ``taught/first/``, where a run
    made before ``then`` was set is moved (its work is the same, so it continues or stands as it ended); then
    the second from the first's best network, in ``taught/`` itself. The summary is the second's, with the
    first's beside it (``first``) and one history of both (seconds added up)."""
    out = layout.finetune_dir(cfg.domain, TAUGHT)
    if cfg.then is None:
        summary = _segment(cfg, start, layout, out, log)
    else:
        summary = _two_segments(cfg, start, layout, out, log)
        atomic_write_text(out / SUMMARY, json.dumps(summary, indent=2) + "\n")
    atomic_write_text(layout.finetune_summary(cfg.domain, TAUGHT), json.dumps(summary, indent=2) + "\n")
    return {k: v for k, v in summary.items() if k != "history"}


def _two_segments(cfg: TeachConfig, start: Path, layout: Layout, out: Path, log) -> dict:
    """The first segment in ``out/first/`` (adopting a finished run of it from ``out``), the second in ``out``;
    the summary of both."""
    first_dir = out / FIRST
    _check_sizes(cfg, start)
    first = _segment(replace(cfg, then=None), start, layout, first_dir, log, adopt=out)
    second_cfg = replace(cfg, then=None, grow=cfg.then.grow, init=str(first_dir / BEST),
                         train=replace(cfg.train, max_epochs=cfg.then.max_epochs))
    log(f"teach {cfg.domain}: the second segment, from the first's best (epoch {first['best_unit']})")
    second = _segment(second_cfg, first_dir / BEST, layout, out, log, where=f"teach.{cfg.domain}.then")
    first_seconds = first["history"][-1]["seconds"] if first["history"] else 0.0
    # the stage's start was grown by the first segment's sizes (``grow``), not the second's
    summary = {**second, "init": str(cfg.init), "init_network_sha256": first["init_network_sha256"],
               **({"grow": cfg.grow.asked()} if cfg.grow.asked() else {}),
               "then": {"grow": cfg.then.grow.asked(), "max_epochs": cfg.then.max_epochs,
                        "start_network_sha256": second["init_network_sha256"]},
               "first": {k: v for k, v in first.items() if k != "history"},
               "units": first["units"] + second["units"], "best_unit": first["units"] + second["best_unit"],
               "train_seconds": round(first["train_seconds"] + second["train_seconds"], 1),
               "steps": first["steps"] + second["steps"], "max_epochs": cfg.train.max_epochs,
               "history": first["history"] + [{**r, "seconds": first_seconds + r["seconds"]}
                                              for r in second["history"]]}
    if not cfg.grow.asked():
        summary.pop("grow", None)
    return summary


def _check_sizes(cfg: TeachConfig, start: Path) -> None:
    """Both segments' sizes against the start's before any training (ConfigError naming the key)."""
    from plad.model.checkpoint import load_model
    from plad.model.grow import grown_config

    model_cfg = load_model(start, expect_domain=cfg.domain)[0].cfg
    for where, grow in ((f"teach.{cfg.domain}.grow", cfg.grow), (f"teach.{cfg.domain}.then.grow", cfg.then.grow)):
        try:
            model_cfg = grown_config(model_cfg, **grow.asked())
        except ValueError as err:
            raise ConfigError(f"{where}: {err}") from None


def _adopt(source: Path, out: Path, fingerprint: dict) -> None:
    """Move a segment's files from ``source`` into ``out`` where ``source`` holds this very work and ``out``
    does not (a run made before a second segment was asked for becomes the first segment)."""
    if resumes(out / LAST, fingerprint) or not (source / LAST).exists() or not resumes(source / LAST, fingerprint):
        return
    for name in SEGMENT_FILES:
        if (source / name).exists():
            os.replace(source / name, out / name)


def _segment(cfg: TeachConfig, start: Path, layout: Layout, out: Path, log=print, adopt: Path | None = None,
             where: str | None = None) -> dict:
    """One teaching segment into ``out`` (its ``summary.json`` there); the summary with its history.
    ``adopt``: a folder whose run of this work moves into ``out`` first."""
    from plad.data.files import evenly_spaced_index, load_prepared, load_split
    from plad.device import resolve_device, resolve_precision
    from plad.domains import get_domain
    from plad.fsutil import sha256_file
    from plad.learn.labels import load_labels
    from plad.learn.loop import Objective, budget_seconds
    from plad.learn.methods import Mixture, mixture_batches
    from plad.learn.rounds import mean_metric
    from plad.learn.train import FitSetup, fit
    from plad.model.checkpoint import load_model, network_digest
    from plad.model.grow import grow
    from plad.provenance import stamp
    from plad.rewrite.pool import pad_programs

    started = time.monotonic()
    where = where or f"teach.{cfg.domain}"
    check(cfg, where)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    device = resolve_device(cfg.device)
    model, name = load_model(start, device, expect_domain=cfg.domain)
    domain = get_domain(name)
    labels_file = layout.labels(cfg.domain)
    labels = load_labels(labels_file)
    n = len(labels) if cfg.label_limit is None else min(len(labels), cfg.label_limit)
    shapes = load_prepared(layout.prepared(cfg.domain), "train")
    real = shapes[labels.index[:n]]
    programs = pad_programs(labels.programs[:n], domain.tokens.max_len)
    executions = labels.executions[:n]
    val = load_split(layout.prepared(cfg.domain), "val", cfg.val_limit)[0]
    fit_idx = evenly_spaced_index(n, min(cfg.fit_shapes, n)) if cfg.fit_shapes else np.zeros(0, np.int64)
    fit_real = real[fit_idx]
    torch.manual_seed(cfg.seed)
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    if cfg.grow.asked():   # after seeding: the new weights are drawn from torch's generator
        try:
            model = grow(model, **cfg.grow.asked())
        except ValueError as err:
            raise ConfigError(f"{where}.grow: {err}") from None
        log(f"teach {cfg.domain}: the start grown to " + ", ".join(f"{k} {v}" for k, v in cfg.grow.asked().items()))

    out.mkdir(parents=True, exist_ok=True)
    metric = domain.metric
    weights = {k: w for k, w in cfg.sources.items() if w > 0}
    total = sum(weights.values())
    mixture = Mixture(tuple(weights), tuple(w / total for w in weights.values()))
    sources = label_sources(domain, real, programs, executions, cfg, device)
    batches = mixture_batches(mixture, sources, cfg.train.batch_size, seed=cfg.seed * 7919 + 58,
                              bucket_pool=cfg.train.bucket_pool)

    def validate(m) -> dict[str, float]:
        row = {"val": mean_metric(m, domain, val, cfg.val_beam, cfg.infer_batch)}
        if len(fit_real):
            row["fit"] = mean_metric(m, domain, fit_real, cfg.fit_beam, cfg.infer_batch)
            row["fit_wide"] = mean_metric(m, domain, fit_real, cfg.fit_beam_wide, cfg.infer_batch)
        return row

    fingerprint = _fingerprint(cfg, sha256_file(labels_file), network_digest(start), n)
    if adopt is not None:
        _adopt(adopt, out, fingerprint)
    history_path = out / HISTORY_FILE
    rows = _history(history_path, out / LAST, fingerprint)

    def on_unit(unit: int, row: dict) -> None:
        nonlocal rows
        rows = [r for r in rows if int(float(r.get("unit", -1))) < unit] + [{"unit": unit, **row}]   # a resumed
        # run redoes the epoch after its last.pt: that row is written again
        _write_history(history_path, rows)
        log(f"teach {cfg.domain}: epoch {unit} " + " ".join(
            f"{k} {v:.4f}" for k, v in row.items() if isinstance(v, float) and k in (
                "train_loss", "val", "fit", "fit_wide", "lr", "unit_seconds")))

    if not rows:   # the starting network's row (epoch 0): where the curve of fit and validation begins
        t0 = time.perf_counter()
        model.eval()
        on_unit(0, {**validate(model), "unit_seconds": time.perf_counter() - t0})
    result = fit(model, batches, validate, cfg.train, out, FitSetup(
        domain.name, domain.tokens.names, objective=Objective("val", metric.higher_is_better),
        budget_seconds=budget_seconds(cfg.max_minutes), on_unit=on_unit, desc=f"teach {cfg.domain}",
        fingerprint=fingerprint, precision=resolve_precision(cfg.precision, device)))
    label_fit = float(labels.values[:n][fit_idx].mean()) if len(fit_idx) else None
    summary = {"key": TAUGHT, "domain": cfg.domain, "metric": metric.name, **result.summary(),
               "labels": n, "labels_mean": round(float(labels.values[:n].mean()), 6),
               "fit_labels_mean": None if label_fit is None else round(label_fit, 6),
               "fit_shapes": int(len(fit_idx)), "val_shapes": int(len(val)),
               "sources": weights, "init": str(cfg.init), "init_network_sha256": network_digest(start),
               **({"grow": cfg.grow.asked()} if cfg.grow.asked() else {}),
               "max_epochs": cfg.train.max_epochs, "steps": result.units * cfg.train.steps_per_epoch,
               "history": [{k: v for k, v in r.items() if k in ("epoch", "val", "fit", "fit_wide", "train_loss",
                                                                 "seconds")} for r in result.history],
               "provenance": stamp(cfg, started)}
    atomic_write_text(out / SUMMARY, json.dumps(summary, indent=2) + "\n")
    return summary
