"""Device choice, arithmetic precision and host-to-device copies, made lazily so that nothing touches CUDA at
import time.

Precision (params ``pretrain.<domain>.precision``, ``finetune.<domain>.precision``): ``fp32`` runs every
forward pass in float32; ``bf16`` runs the training forward passes under bfloat16 autocast (matrix products and
convolutions in bf16, weights, gradients and optimizer state stay float32, so no loss scaling is needed);
``auto`` is bf16 on a CUDA device that computes bf16 natively (compute capability 8.0 and up: A100, H100, RTX 30xx
and later) and fp32 otherwise (an older GPU would emulate bf16, slower than fp32), so a profile that says ``auto``
keeps a CPU run's numbers unchanged. A CPU run may still opt in with ``bf16`` (CPUs with AVX512-BF16 or AMX run it
faster: ``python -m bench.precision``). Decoding (beam search, sampling, validation) stays float32 either way.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
import torch

from plad.config import ConfigError

#: the values of a ``precision`` key
PRECISIONS = ("auto", "bf16", "fp32")
#: the largest relative change of a batch's loss that bf16 autocast may make, against float32 on the same weights
#: and batch (tests/plad/test_device.py on the shipped models; ``bench.gpu_check`` on a GPU). Measured on
#: these CPUs: 1e-4 (trained models, evaluation mode) to 1.2e-3 (training mode, dropout drawn in bf16)
BF16_LOSS_RTOL = 5e-3


@contextlib.contextmanager
def torch_threads(n: int):
    """Run the block with ``n`` torch intra-op threads, then restore the count.

    For work made of many tiny tensor operations, such as the grammar samplers (each program executed on its
    own to check it): spreading an operation on a few hundred elements over a machine's cores only adds
    synchronization. Measured on a 2-core machine: the samplers' programs per CPU second fall 2.5x (2D) to
    5x (3D CSG) with 2 threads instead of 1; ``python -m bench.sampler``. Results do not depend on the
    count (tests/plad/test_device.py)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


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



def check_precision(name: str) -> None:
    """ValueError unless ``name`` is one of :data:`PRECISIONS` (a config class's ``__post_init__`` calls it, so
    that :func:`plad.config.build` reports the file and key)."""
    if name not in PRECISIONS:
        raise ValueError(f"precision {name!r}: use one of {', '.join(PRECISIONS)}")


@dataclass(frozen=True)
class Precision:
    """How a run's training forward passes compute: float32 (``dtype`` None) or autocast to ``dtype`` on
    ``device_type``."""

    device_type: str = "cpu"
    dtype: torch.dtype | None = None

    @property
    def name(self) -> str:
        return "fp32" if self.dtype is None else {torch.bfloat16: "bf16"}.get(self.dtype, str(self.dtype))

    def autocast(self) -> contextlib.AbstractContextManager:
        """The context of a forward pass: autocast to ``dtype``, or nothing at all for float32 (so that an fp32
        run executes exactly the operations it did before this switch existed)."""
        if self.dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(self.device_type, dtype=self.dtype)


#: float32 everywhere: every trainer's default
FP32 = Precision()


def resolve_precision(name: str, device: torch.device) -> Precision:
    """A params value (:data:`PRECISIONS`) for a run on ``device``."""
    check_precision(name)
    if name == "bf16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise ConfigError(f"precision: bf16 was requested but {torch.cuda.get_device_name(device)} does not "
                          f"support bfloat16; use fp32 or auto")
    native = device.type == "cuda" and torch.cuda.get_device_capability(device)[0] >= 8
    if name == "bf16" or (name == "auto" and native):
        return Precision(device.type, torch.bfloat16)
    return Precision(device.type)


def to_device(x: torch.Tensor | np.ndarray, device: torch.device) -> torch.Tensor:
    """``x`` (a tensor or a NumPy array) on ``device``.

    To a CUDA device from host memory the copy goes through pinned (page-locked) memory and does not block:
    the host goes on preparing the next batch while the copy runs, and the GPU's work queue orders the copy
    before any kernel that reads it. On the CPU nothing is copied (a NumPy array is shared, as
    ``torch.from_numpy`` does).
    """
    t = torch.as_tensor(x)
    if device.type != "cuda" or t.device.type != "cpu":
        return t.to(device)
    if not t.is_pinned():
        t = t.pin_memory()
    return t.to(device, non_blocking=True)
