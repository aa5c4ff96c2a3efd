"""When to run the compiled CPU kernels (numba), and whether they can run.

The kernels (the Chamfer metric's, a domain plugin's executor) compute what a tensor path of the same module
computes, to the bit; each caller keeps that path for CUDA and for an install without numba. Loading numba and
the first call into cached kernels cost about a second in a fresh process (0.7-1.4 s measured on the 2-core
machine), more than a short process spends in the work itself: `plad infer` on one shape, a stage of the smoke
profile. So by default (mode None) a process runs the tensor paths until the work it has given them adds up to
:data:`LOAD_SECONDS` (each caller estimates a call's tensor-path seconds), and the compiled kernels from then on,
when loading them has paid for itself; a long search or training gets there in its first seconds. Mode True
compiles from the first call, False never. Compiled code is cached beside its module (``cache=True``).
Nothing here imports numba.
"""
from __future__ import annotations

import importlib
import importlib.util

#: tensor-path seconds a process spends before it loads the compiled kernels (about what loading them costs)
LOAD_SECONDS = 1.0

_spent = 0.0
_loaded = False
_installed: bool | None = None


def installed() -> bool:
    """Whether numba can be imported here (without importing it)."""
    global _installed
    if _installed is None:
        _installed = importlib.util.find_spec("numba") is not None
    return _installed


def use(mode: bool | None, seconds: float) -> bool:
    """Whether a call whose tensor path would take about ``seconds`` runs compiled. ``mode``: a caller's switch,
    True (compiled wherever numba is installed), False (never) or None (once the process has earned it)."""
    global _spent, _loaded
    if mode is False or not installed():
        return False
    if mode is True or _loaded:
        return True
    _spent += seconds
    _loaded = _spent >= LOAD_SECONDS
    return _loaded


def compiler():
    """numba's ``njit``, or None where numba cannot be imported: what a kernel module decorates its kernels with
    (importing numba, so only kernel modules call it)."""
    try:
        from numba import njit
    except ImportError:
        return None
    return njit


def kernels(module: str, mode: bool | None, seconds: float):
    """The kernel module ``module`` (one whose ``njit`` came from :func:`compiler`) where a call whose tensor path
    would take about ``seconds`` should run compiled (:func:`use`) and can, else None."""
    if not use(mode, seconds):
        return None
    found = importlib.import_module(module)
    return found if found.njit is not None else None


def load() -> None:
    """Compile from the next call on, as a process does once it has earned it (a benchmark's steady state)."""
    global _loaded
    _loaded = True


def reset() -> None:
    """Back to a fresh process's state (tests)."""
    global _spent, _loaded
    _spent, _loaded = 0.0, False
