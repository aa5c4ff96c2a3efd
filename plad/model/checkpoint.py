"""Model checkpoints that rebuild the network from the file alone.

A checkpoint holds the model config, the domain name and its token names
(checked on load, so a checkpoint never silently decodes with another
vocabulary), the weights, and optionally training state for resuming.
Writes are atomic.

A checkpoint holds only tensors and plain data (str, int, float, bool, None,
and lists, tuples and dicts of them): it is read with
``torch.load(weights_only=True)``, so a file from ``--model``, the MLflow
registry or anywhere else cannot run code when it is loaded. A file holding
anything else is refused with one line (:class:`CheckpointError`). Files
written by versions that pickled other objects (NumPy's RNG state) are
converted once, from a trusted source only, by::

    python -m plad.model.checkpoint convert OLD.pt NEW.pt
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import pickle
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from plad.domains import get_domain
from plad.errors import RunFailure, one_line
from plad.fsutil import atomic_write
from plad.model.network import ModelConfig, PLADNet

FORMAT = "plad-checkpoint-1"


class CheckpointError(RunFailure):
    """A checkpoint cannot be used; the message is one line naming the file (exit status 1)."""


#: how :func:`read_checkpoint` tells the user to convert a checkpoint of an older version
CONVERT_HINT = "python -m plad.model.checkpoint convert OLD NEW"
_PLAIN = (str, int, float, bool, type(None), torch.Tensor, torch.Size)


def plain(value: Any, where: str = "checkpoint") -> Any:
    """``value`` as tensors and plain data only; NumPy arrays and scalars become tensors and numbers.

    Raises ``TypeError`` naming the key for anything else, so a checkpoint that
    ``torch.load(weights_only=True)`` could not read is never written.
    """
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, np.generic):   # before the plain types: np.float64 is a float subclass
        return value.item()
    if isinstance(value, _PLAIN):
        return value
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(value))
    if isinstance(value, dict):
        return {k: plain(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(plain(v, f"{where}[{i}]") for i, v in enumerate(value))
    raise TypeError(f"{where}: a {type(value).__name__} is not plain data (tensors, numbers, strings, "
                    "lists, dicts)")


def save_checkpoint(path: str | os.PathLike, model: PLADNet, domain: str, token_names: list[str],
                    extra: dict[str, Any] | None = None) -> Path:
    payload = {
        "format": FORMAT,
        "domain": domain,
        "tokens": list(token_names),
        "config": model.cfg.to_dict(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        **plain(extra or {}, "extra"),
    }
    buf = io.BytesIO()
    torch.save(payload, buf)
    return atomic_write(path, lambda fh: fh.write(buf.getvalue()))


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: no such checkpoint")
    try:
        # weights_only: only tensors and plain containers are unpickled; nothing in the file can run
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise CheckpointError(f"{path}: holds objects other than tensors and plain data; refused (a checkpoint "
                              f"of an older PLAD version from a source you trust: `{CONVERT_HINT}`)") from None
    except Exception as err:  # torch raises many types for corrupt files
        raise CheckpointError(f"{path}: not a readable checkpoint ({err.__class__.__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a PLAD checkpoint (expected format {FORMAT})")
    return payload


def network_digest(path: str | os.PathLike) -> str:
    """sha256 of the network a checkpoint holds: its domain, tokens, config and weights (names, dtypes, shapes,
    values), not the bytes of the file, which also hold the wall-clock provenance of its training (two runs
    that train the same weights write files that differ in their seconds)."""
    payload = read_checkpoint(path)
    h = hashlib.sha256()
    h.update(json.dumps([payload.get("domain"), payload.get("tokens"), payload.get("config")],
                        sort_keys=True).encode())
    for name, tensor in sorted(payload.get("state_dict", {}).items()):
        t = tensor.detach().cpu()
        h.update(f"\n{name} {t.dtype} {tuple(t.shape)}\n".encode())
        h.update(t.contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


#: the largest network a checkpoint may declare (parameters): the project's are a few million; a config
#: declaring more (e.g. 17 GB of weights) is refused before anything is allocated
MAX_PARAMETERS = 200_000_000
#: the most encoder blocks plus decoder layers a checkpoint may declare (each is a module to build)
MAX_BLOCKS = 64


def estimate_parameters(cfg: ModelConfig) -> int:
    """An estimate of the network's parameter count from its config alone (no module is built)."""
    dims = len(cfg.input_shape)
    kernel = (cfg.enc_kernel or (3 if dims == 2 else 4)) ** dims
    channels = [1 + dims, *cfg.enc_channels]
    convs = sum(a * b * kernel for a, b in zip(channels, channels[1:]))
    d = cfg.d_model
    return convs + channels[-1] * d + cfg.n_layers * (4 * d * d + 2 * d * cfg.dim_ff) + 4 * d * d \
        + (cfg.vocab_size + cfg.max_len + 2) * d


def check_checkpoint(path: str | os.PathLike, payload: dict[str, Any], expect_domain: str | None = None
                     ) -> tuple[ModelConfig, str]:
    """(config, domain) of a read checkpoint, after checking it can be built and loaded as it claims: its
    entries, a known domain with this version's tokens, a valid config of that domain's sizes (types, values,
    no unknown key), a network of at most :data:`MAX_PARAMETERS` parameters, and weights of exactly the
    network's names and shapes, all finite. Anything else is a :class:`CheckpointError` naming what is wrong,
    raised before the network is built."""
    from plad.config import ConfigError, build

    missing = [k for k in ("domain", "tokens", "config", "state_dict") if k not in payload]
    if missing:
        raise CheckpointError(f"{path}: no {', '.join(map(repr, missing))} entry: not a complete PLAD checkpoint")
    domain = payload["domain"]
    if not isinstance(domain, str):
        raise CheckpointError(f"{path}: its domain is {domain!r}, not a domain name")
    if expect_domain is not None and domain != expect_domain:
        raise CheckpointError(f"{path}: a {domain} model, not a {expect_domain} one")
    try:
        spec = get_domain(domain)
    except KeyError:
        raise CheckpointError(f"{path}: unknown domain {domain!r}") from None
    if spec.tokens.names != payload["tokens"]:
        raise CheckpointError(f"{path}: its {domain} vocabulary differs from this version's token table")
    try:
        cfg = build(ModelConfig, payload["config"], "config", source=str(path))
    except ConfigError as err:
        raise CheckpointError(str(err)) from None
    want = {"vocab_size": len(spec.tokens), "max_len": spec.tokens.max_len, "input_shape": tuple(spec.shape)}
    for key, value in want.items():
        if getattr(cfg, key) != value:
            raise CheckpointError(f"{path}: config.{key} = {getattr(cfg, key)!r}, but a {domain} network has "
                                  f"{value!r}")
    if cfg.n_layers + len(cfg.enc_channels) > MAX_BLOCKS or estimate_parameters(cfg) > MAX_PARAMETERS:
        raise CheckpointError(f"{path}: its config declares a network of about {estimate_parameters(cfg):,} parameters "
                              f"in {cfg.n_layers + len(cfg.enc_channels)} blocks, more than the limit of "
                              f"{MAX_PARAMETERS:,} in {MAX_BLOCKS}")
    try:
        with torch.device("meta"):   # shapes without memory: what the weights must match
            expected = {k: v.shape for k, v in PLADNet(cfg).state_dict().items()}
    except (RuntimeError, ValueError) as err:   # e.g. more poolings than the input has pixels
        raise CheckpointError(f"{path}: its config builds no network ({one_line(err)[:200]})") from None
    if sum(int(np.prod(s)) for s in expected.values()) > MAX_PARAMETERS:
        raise CheckpointError(f"{path}: its config declares more than {MAX_PARAMETERS:,} parameters")
    weights = payload["state_dict"]
    if not isinstance(weights, dict):
        raise CheckpointError(f"{path}: its weights are not a mapping of names to tensors")
    absent = sorted(set(expected) - set(weights))
    extra = sorted(set(weights) - set(expected))
    if absent or extra:
        parts = ([f"missing weights {', '.join(absent[:3])}{' ...' if len(absent) > 3 else ''}"] if absent else []) \
            + ([f"unexpected weights {', '.join(extra[:3])}{' ...' if len(extra) > 3 else ''}"] if extra else [])
        raise CheckpointError(f"{path}: {'; '.join(parts)} for its config")
    for name, shape in expected.items():
        tensor = weights[name]
        if not isinstance(tensor, torch.Tensor) or tensor.shape != shape:
            got = tuple(tensor.shape) if isinstance(tensor, torch.Tensor) else type(tensor).__name__
            raise CheckpointError(f"{path}: weight {name} is {got}, its config needs {tuple(shape)}")
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{path}: weight {name} holds NaN or infinite values")
        if tensor.is_floating_point() and tensor.numel() and float(tensor.abs().max()) > MAX_WEIGHT:
            raise CheckpointError(f"{path}: weight {name} holds values up to {float(tensor.abs().max()):.3g}, "
                                  f"beyond {MAX_WEIGHT:g}: a diverged or damaged network")
    return cfg, domain


#: the largest magnitude of a weight (the shipped networks' largest is about 38): beyond it a network has
#: diverged or been damaged, and its forward passes overflow
MAX_WEIGHT = 1e4


# ---- training state ----------------------------------------------------------------------------------
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
    import random

    if cfg is None:
        cfg, _ = check_checkpoint(path, payload)
    where = f"{path}:"
    for key in ("optimizer", "scheduler", "rng"):
        if key not in payload:
            raise CheckpointError(f"{where} no {key!r} entry: not a training state to continue")
    # -- optimizer
    with torch.device("meta"):
        shapes = [tuple(p.shape) for p in PLADNet(cfg).parameters()]
    opt = payload["optimizer"]
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
    # -- learning-rate schedule (a plateau rule)
    sched = payload["scheduler"]
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
    # -- random number generators: each state set on a fresh generator
    rng = payload["rng"]
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


def _check_loop(where: str, payload: dict[str, Any]) -> dict[str, Any]:
    """The loop state of a training checkpoint (``loop``, or an older ``train_state``), checked."""
    from plad.learn.loop import upgrade_state

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
    from plad.learn.pretrain import totals

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


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu",
               expect_domain: str | None = None) -> tuple[PLADNet, str]:
    """(model in eval mode on ``device``, domain name) from a checkpoint file, checked first
    (:func:`check_checkpoint`)."""
    payload = read_checkpoint(path)
    cfg, domain = check_checkpoint(path, payload, expect_domain)
    model = PLADNet(cfg)
    model.load_state_dict(payload["state_dict"])
    return model.to(device).eval(), domain


def convert(old: str | os.PathLike, new: str | os.PathLike) -> Path:
    """Rewrite a checkpoint of an older version as tensors and plain data (:func:`plain`).

    This unpickles ``old`` fully (``weights_only=False``): run it only on files
    you trust, once; the result loads with ``weights_only=True``.
    """
    old = Path(old)
    if not old.is_file():
        raise CheckpointError(f"{old}: no such checkpoint")
    try:
        payload = torch.load(old, map_location="cpu", weights_only=False)
    except Exception as err:  # torch raises many types for corrupt files
        raise CheckpointError(f"{old}: not a readable checkpoint ({err.__class__.__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") not in (FORMAT, None):
        raise CheckpointError(f"{old}: not a PLAD checkpoint")
    try:
        payload = plain(payload)
    except TypeError as err:
        raise CheckpointError(f"{old}: cannot convert: {err}") from None
    buf = io.BytesIO()
    torch.save(payload, buf)
    return atomic_write(new, lambda fh: fh.write(buf.getvalue()))


def main(argv: list[str] | None = None) -> int:
    """``python -m plad.model.checkpoint convert OLD NEW``: the one-off conversion of an older checkpoint."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m plad.model.checkpoint",
                                     description="Convert a checkpoint of an older PLAD version (trusted files "
                                                 "only) to tensors and plain data.")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("convert", help="rewrite OLD (fully unpickled: trusted files only) as NEW")
    p.add_argument("old")
    p.add_argument("new")
    args = parser.parse_args(argv)
    try:
        out = convert(args.old, args.new)
    except CheckpointError as err:
        print(f"plad.model.checkpoint: error: {err}", file=sys.stderr)
        return 1
    print(f"converted {args.old} -> {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
