"""The one check of a checkpoint's training state before any training continues from it or a command ships
it (:func:`check_training_state`), and the totals of a pretraining's provenance segments (:func:`totals`).

In the learning layer (it reads the loop's state and the pretraining's provenance), above
:mod:`plad.model.checkpoint`, whose :func:`~plad.model.checkpoint.check_checkpoint` checks the network alone.
"""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import torch

from plad.errors import one_line
from plad.learn.loop import upgrade_state
from plad.model.checkpoint import CheckpointError, check_checkpoint
from plad.model.network import ModelConfig, PLADNet


def totals(segments: list[dict]) -> dict:
    """What the segments hold together; ``cpu_hours`` sums the segments that know theirs (all: ``complete``)."""
    known = [s["cpu_hours"] for s in segments if s.get("cpu_hours") is not None]
    return {"segments": len(segments),
            "epochs": sum(s["epochs"][1] - s["epochs"][0] + 1 for s in segments),
            "steps": sum(s["steps"] for s in segments), "shapes_seen": sum(s["shapes_seen"] for s in segments),
            "train_seconds": round(sum(s["train_seconds"] for s in segments), 1),
            "cpu_hours": round(sum(known), 3), "cpu_hours_complete": len(known) == len(segments),
            "gpu_hours": round(sum(s.get("gpu_hours") or 0 for s in segments), 3)}


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _finite_tensor(t: Any) -> bool:
    return isinstance(t, torch.Tensor) and (not t.is_floating_point() or bool(torch.isfinite(t).all()))


def check_training_state(path: str | os.PathLike, payload: dict[str, Any], cfg: ModelConfig | None = None) -> None:
    """The one check of a checkpoint's training state before any training continues from it (a resumed
    ``last.pt``, ``pretrain.init``) or a command ships it: :class:`CheckpointError`, one line naming the part
    that is wrong, unless

    * the network passes :func:`check_checkpoint` (finite weights of the config's names and shapes);
    * the optimizer's state is Adam's of exactly this network: one group whose parameter ids are 0..n-1, a
      finite positive learning rate, and per parameter a finite step and finite ``exp_avg`` / non-negative
      ``exp_avg_sq`` moments of the parameter's shape;
    * the learning-rate schedule's state is a plateau rule's, with numbers where it keeps numbers;
    * the RNG states are the generators' own (each is set on a fresh generator to try it);
    * the loop state holds counts that agree (``0 <= segment_unit <= unit``, ``best_unit <= unit``, seconds
      finite and non-negative, history rows of increasing units up to ``unit`` holding numbers);
    * a curriculum state, where there is one, holds its counts;
    * the provenance, where there is one, holds segments of contiguous epochs ending at the loop's unit,
      whose totals are the ones recorded.
    """
    if cfg is None:
        cfg, _ = check_checkpoint(path, payload)
    where = f"{path}:"
    for key in ("optimizer", "scheduler", "rng"):
        if key not in payload:
            raise CheckpointError(f"{where} no {key!r} entry: not a training state to continue")
    _check_optimizer(where, payload["optimizer"], cfg)
    _check_schedule(where, payload["scheduler"])
    _check_rng(where, payload["rng"])
    # -- loop state
    loop = _check_loop(where, payload)
    # -- curriculum
    stages = payload.get("stages")
    if stages is not None:
        if not isinstance(stages, dict) or not all(_is_int(stages.get(k)) and stages[k] >= 0
                                                   for k in ("stage", "stage_steps", "stale")) or \
                not _is_number(stages.get("best_loss")) or math.isnan(stages["best_loss"]):
            raise CheckpointError(f"{where} its curriculum state is not one (stage, stage_steps, stale, best_loss)")
    # -- provenance
    if "provenance" in payload:
        _check_provenance(where, payload["provenance"], loop["unit"])


def _check_optimizer(where: str, opt: Any, cfg: ModelConfig) -> None:
    """Adam's state of exactly the network of ``cfg`` (see :func:`check_training_state`)."""
    with torch.device("meta"):
        shapes = [tuple(p.shape) for p in PLADNet(cfg).parameters()]
    if not isinstance(opt, dict) or not isinstance(opt.get("state"), dict) or \
            not isinstance(opt.get("param_groups"), list) or len(opt["param_groups"]) != 1 or \
            not isinstance(opt["param_groups"][0], dict):
        raise CheckpointError(f"{where} the optimizer state is not Adam's of one parameter group")
    group = opt["param_groups"][0]
    if group.get("params") != list(range(len(shapes))):
        raise CheckpointError(f"{where} the optimizer's parameter ids are not 0..{len(shapes) - 1}, the network's "
                              f"{len(shapes)} parameters")
    lr = group.get("lr")
    if not _is_number(lr) or not math.isfinite(lr) or lr <= 0:
        raise CheckpointError(f"{where} the optimizer's learning rate is {lr!r}, not a finite positive number")
    for key in ("eps", "weight_decay"):
        if key in group and (not _is_number(group[key]) or not math.isfinite(group[key]) or group[key] < 0):
            raise CheckpointError(f"{where} the optimizer's {key} is {group[key]!r}")
    betas = group.get("betas", (0.9, 0.999))
    if not isinstance(betas, (list, tuple)) or len(betas) != 2 or \
            not all(_is_number(b) and 0 <= b < 1 for b in betas):
        raise CheckpointError(f"{where} the optimizer's betas are {betas!r}")
    for pid, state in opt["state"].items():
        if not _is_int(pid) or not 0 <= pid < len(shapes):
            raise CheckpointError(f"{where} the optimizer holds state for parameter {pid!r}, which the network "
                                  f"does not have")
        if not isinstance(state, dict) or not {"step", "exp_avg", "exp_avg_sq"} <= set(state):
            raise CheckpointError(f"{where} the optimizer state of parameter {pid} is not Adam's")
        step = state["step"]
        value = float(step) if isinstance(step, torch.Tensor) and step.numel() == 1 else step
        if not _is_number(value) or not math.isfinite(value) or value < 0:
            raise CheckpointError(f"{where} the optimizer step of parameter {pid} is {step!r}")
        for key in ("exp_avg", "exp_avg_sq"):
            t = state[key]
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shapes[pid]:
                got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                raise CheckpointError(f"{where} the optimizer's {key} of parameter {pid} is {got}, the parameter "
                                      f"is {shapes[pid]}")
            if not _finite_tensor(t):
                raise CheckpointError(f"{where} the optimizer's {key} of parameter {pid} holds NaN or infinite "
                                      f"values (Adam's moments of a diverged or damaged run)")
        if bool((state["exp_avg_sq"] < 0).any()):
            raise CheckpointError(f"{where} the optimizer's exp_avg_sq of parameter {pid} holds negative values")


def _check_schedule(where: str, sched: Any) -> None:
    """A plateau rule's state, with numbers where it keeps numbers."""
    if not isinstance(sched, dict):
        raise CheckpointError(f"{where} the learning-rate schedule's state is not a mapping")
    if sched.get("mode", "min") not in ("min", "max") or sched.get("threshold_mode", "abs") not in ("rel", "abs"):
        raise CheckpointError(f"{where} the learning-rate schedule's mode is {sched.get('mode')!r} / "
                              f"{sched.get('threshold_mode')!r}")
    for key in ("num_bad_epochs", "last_epoch", "cooldown_counter", "cooldown", "patience"):
        if key in sched and (not _is_int(sched[key]) or sched[key] < (-1 if key == "last_epoch" else 0)):
            raise CheckpointError(f"{where} the learning-rate schedule's {key} is {sched[key]!r}")
    for key in ("best", "mode_worse", "factor", "threshold", "eps"):
        if key in sched and (not _is_number(sched[key]) or math.isnan(sched[key])):
            raise CheckpointError(f"{where} the learning-rate schedule's {key} is {sched[key]!r}")
    for key in ("_last_lr", "min_lrs"):
        if key in sched and (not isinstance(sched[key], (list, tuple)) or
                             not all(_is_number(v) and math.isfinite(v) and v >= 0 for v in sched[key])):
            raise CheckpointError(f"{where} the learning-rate schedule's {key} is {sched[key]!r}")


def _check_rng(where: str, rng: Any) -> None:
    """The generators' states: each set on a fresh generator."""
    import random

    try:
        if not isinstance(rng, dict):
            raise TypeError("not a mapping")
        torch.Generator().set_state(rng["torch"])
        name, keys, *rest = rng["numpy"]
        np.random.RandomState().set_state((name, np.asarray(keys, dtype=np.uint32), *rest))
        random.Random().setstate(tuple(rng["python"]) if isinstance(rng["python"], list) else rng["python"])
    except Exception as err:   # each generator raises its own types for a state it cannot take
        raise CheckpointError(f"{where} its random generators' state cannot be restored "
                              f"({err.__class__.__name__}: {one_line(err)[:120]})") from None


def _check_loop(where: str, payload: dict[str, Any]) -> dict[str, Any]:
    """The loop state of a training checkpoint (``loop``, or an older ``train_state``), checked."""

    raw = payload.get("loop", payload.get("train_state"))
    if not isinstance(raw, dict):
        raise CheckpointError(f"{where} no loop state ('loop' entry) to continue")
    try:
        loop = upgrade_state(raw, "epoch")
    except (KeyError, TypeError, AttributeError) as err:
        raise CheckpointError(f"{where} its loop state is not one ({err.__class__.__name__}: {err})") from None
    unit = loop.get("unit")
    if not _is_int(unit) or unit < 0:
        raise CheckpointError(f"{where} loop.unit = {unit!r}: not a count of finished epochs")
    for key, low, high in (("segment_unit", 0, unit), ("best_unit", 0, unit)):
        v = loop.get(key, 0)
        if not _is_int(v) or not low <= v <= high:
            raise CheckpointError(f"{where} loop.{key} = {v!r}: expected a count from {low} to loop.unit ({unit})")
    seconds = loop.get("seconds", 0.0)
    for key in ("seconds", "segment_seconds", "since_best"):
        v = loop.get(key, 0.0)
        if not _is_number(v) or not math.isfinite(v) or v < 0:
            raise CheckpointError(f"{where} loop.{key} = {v!r}: expected a finite number, 0 or more")
    if loop.get("segment_seconds", 0.0) > seconds + 1e-6:
        raise CheckpointError(f"{where} loop.segment_seconds is more than loop.seconds")
    best = loop.get("best")
    if not _is_number(best) or math.isnan(best):
        raise CheckpointError(f"{where} loop.best = {best!r}: not a number (a diverged run?)")
    history = loop.get("history", [])
    if not isinstance(history, list):
        raise CheckpointError(f"{where} loop.history is not a list of rows")
    last = -1
    for i, row in enumerate(history):
        if not isinstance(row, dict) or not _is_int(row.get("unit")) or not last < row["unit"] <= unit:
            raise CheckpointError(f"{where} loop.history row {i} is not a row of an epoch after the one before it "
                                  f"and up to loop.unit ({unit})")
        last = row["unit"]
        for key, v in row.items():   # a metric may be NaN or infinite (a row says what was measured)
            if not isinstance(key, str) or not (_is_number(v) or isinstance(v, bool)):
                raise CheckpointError(f"{where} loop.history row {i} holds {key!r} = {v!r}, not a number")
        if row["unit"] > 0 and not {"val", "unit_seconds", "seconds"} <= set(row):
            raise CheckpointError(f"{where} loop.history row {i} lacks val, unit_seconds or seconds")
    return loop


def _check_provenance(where: str, prov: Any, unit: int) -> None:
    """Provenance segments of contiguous epochs ending at ``unit``, and the totals they add up to."""

    segments = prov.get("segments") if isinstance(prov, dict) else None
    if not isinstance(segments, list) or not segments or not all(isinstance(s, dict) for s in segments):
        raise CheckpointError(f"{where} provenance.segments is not a list of segments")
    start = 1
    for i, s in enumerate(segments):
        epochs = s.get("epochs")
        if not (isinstance(epochs, list) and len(epochs) == 2 and all(_is_int(e) for e in epochs)) or \
                epochs[0] != start or epochs[1] < epochs[0] - 1:
            raise CheckpointError(f"{where} provenance segment {i} covers epochs {epochs!r}, expected [{start}, N]")
        for key in ("steps", "shapes_seen", "train_seconds"):
            if not _is_number(s.get(key)) or not math.isfinite(s[key]) or s[key] < 0:
                raise CheckpointError(f"{where} provenance segment {i} has {key} = {s.get(key)!r}")
        for key in ("cpu_hours", "gpu_hours"):
            if s.get(key) is not None and (not _is_number(s[key]) or not math.isfinite(s[key]) or s[key] < 0):
                raise CheckpointError(f"{where} provenance segment {i} has {key} = {s[key]!r}")
        start = epochs[1] + 1
    if start - 1 != unit:
        raise CheckpointError(f"{where} its provenance segments end at epoch {start - 1}, its loop state at {unit}")
    recorded = prov.get("totals")
    expected = totals(segments)
    if not isinstance(recorded, dict) or any(
            not (_is_number(recorded.get(k)) or isinstance(recorded.get(k), bool)) or
            abs(float(recorded[k]) - float(v)) > 0.01 + 1e-6 * abs(float(v)) for k, v in expected.items()):
        raise CheckpointError(f"{where} provenance.totals {recorded!r} are not the totals of its segments")
