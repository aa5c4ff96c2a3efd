"""Device choice, made lazily so that nothing touches CUDA at import time."""
from __future__ import annotations

import torch


def default_device() -> torch.device:
    """CUDA when a GPU is present, otherwise the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")
