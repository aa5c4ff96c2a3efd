"""Device choice, made lazily so that nothing touches CUDA at import time."""
from __future__ import annotations

import torch

from plad.config import ConfigError


def default_device() -> torch.device:
    """CUDA when a GPU is present, otherwise the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def resolve_device(name: str) -> torch.device:
    """A params value: "auto" (CUDA when present), "cpu" or "cuda"."""
    if name == "auto":
        return default_device()
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device: cuda was requested but no CUDA device is available")
    return torch.device(name)
