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
