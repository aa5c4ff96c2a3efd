"""Device choice, made lazily so that nothing touches CUDA at import time."""
from __future__ import annotations

import torch

from plad.config import ConfigError


def default_device() -> torch.device:
    """CUDA when a GPU is present, otherwise the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def resolve_device(name: str) -> torch.device:
    """A params value: "auto" (CUDA when present), "cpu", "cuda" or "cuda:N"."""
    if name == "auto":
        return default_device()
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device: {name} was requested but no CUDA device is available")
    try:
        return torch.device(name)
    except RuntimeError:   # a name torch does not know, e.g. "tpu" (params checks it first: plad.config)
        raise ConfigError(f"device: {name!r} is not a device; use auto, cpu, cuda or cuda:N") from None
