"""Where a result comes from: the git commit of the code (and whether the tree was dirty) and the machine.

Read once per process; no network, no torch import (the machine's GPU is read only when torch is already
imported by the caller).
"""
from __future__ import annotations

import os
import platform
import subprocess
import sys
from functools import cache
from pathlib import Path

_PACKAGE_ROOT = Path(__file__).resolve().parent.parent


def _git(*args: str, cwd: Path) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


@cache
def code_state(root: str | None = None) -> dict[str, object]:
    """``{"commit": sha or None, "dirty": bool or None}`` of the checkout holding the code (default: this
    package's); ``dirty`` counts tracked files only (results written by a run do not make it dirty)."""
    cwd = Path(root) if root else _PACKAGE_ROOT
    commit = _git("rev-parse", "HEAD", cwd=cwd)
    status = _git("status", "--porcelain", "--untracked-files=no", cwd=cwd) if commit else None
    return {"commit": commit, "dirty": bool(status) if status is not None else None}


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, object]:
    """The CPU model, its cores (those this process may use) and the GPU when torch sees one."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    out: dict[str, object] = {"cpu": _cpu_model(), "cores": cores, "gpu": None}
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        out["gpu"] = torch.cuda.get_device_name(0)
    return out
