"""Model checkpoints that rebuild the network from the file alone.

A checkpoint holds the model config, the domain name and its token names
(checked on load, so a checkpoint never silently decodes with another
vocabulary), the weights, and optionally training state for resuming.
Writes are atomic.
"""
from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import torch

from plad.domains import get_domain
from plad.fsutil import atomic_write
from plad.model import ModelConfig, PLADNet

FORMAT = "plad-checkpoint-1"


class CheckpointError(Exception):
    """A checkpoint cannot be used; the message is one line naming the file."""


def save_checkpoint(path: str | os.PathLike, model: PLADNet, domain: str, token_names: list[str],
                    extra: dict[str, Any] | None = None) -> Path:
    payload = {
        "format": FORMAT,
        "domain": domain,
        "tokens": list(token_names),
        "config": model.cfg.to_dict(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        **(extra or {}),
    }
    buf = io.BytesIO()
    torch.save(payload, buf)
    return atomic_write(path, lambda fh: fh.write(buf.getvalue()))


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: no such checkpoint")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # torch raises many types for corrupt files
        raise CheckpointError(f"{path}: not a readable checkpoint ({err.__class__.__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a PLAD checkpoint (expected format {FORMAT})")
    return payload


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu",
               expect_domain: str | None = None) -> tuple[PLADNet, str]:
    """(model in eval mode on ``device``, domain name) from a checkpoint file."""
    payload = read_checkpoint(path)
    domain = payload["domain"]
    if expect_domain is not None and domain != expect_domain:
        raise CheckpointError(f"{path}: a {domain} model, not a {expect_domain} one")
    try:
        names = get_domain(domain).tokens.names
    except KeyError:
        raise CheckpointError(f"{path}: unknown domain {domain!r}") from None
    if names != payload["tokens"]:
        raise CheckpointError(f"{path}: its {domain} vocabulary differs from this version's token table")
    model = PLADNet(ModelConfig(**payload["config"]))
    model.load_state_dict(payload["state_dict"])
    return model.to(device).eval(), domain
