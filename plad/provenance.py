"""Where a number comes from: the commit of the code, the params, the threads, the time and the machine.

Every metrics file a stage writes carries a ``provenance`` block (:func:`stamp`)::

    {"commit": "<sha>" or null, "dirty": bool or null, "params_hash": "<16 hex>", "torch_threads": int or null,
     "wall_seconds": float, "machine": {"cpu": str, "cores": int, "gpu": str or null}}

``commit`` is the git commit of the checkout holding this package (null outside git); ``dirty`` says
whether the code (the package folder) or the params files (``params.yaml``, ``profiles/``) differ from
it, untracked files there included. Result files written by a run (``results/``, ``dvc.lock``) do not
count: a pipeline run modifies them stage after stage, and they do not change a number. ``params_hash``
is a hash of the stage's resolved params (the config it built: ``base``, domain block, profile and
``--set`` overrides applied), so two numbers with the same hash come from the same settings.
:func:`code_state` and :func:`params_hash` are the one home of both: a shipped model's sidecar records the
same git state, and a stage's MLflow run folder the same params hash (:class:`plad.tracking.runs.StageRun`).
``wall_seconds`` is the time of the call that wrote the file.

A rerun of a stage at the same commit, params and thread count gives the same numbers (issue 33);
:func:`without_timing` drops what may differ between two such runs (wall-clock measurements and this
block), which is what the determinism test compares.

No network, no torch import: the thread count and the GPU are read only from a torch the caller has
imported already.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Mapping
from functools import cache
from pathlib import Path
from typing import Any

_PACKAGE_DIR = Path(__file__).resolve().parent
#: what ``dirty`` looks at, relative to the checkout's root: the code and the params files
CODE_PATHS = (_PACKAGE_DIR.name, "params.yaml", "profiles")


def _git(*args: str, cwd: Path) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


@cache
def code_state(root: str | None = None) -> dict[str, Any]:
    """``{"commit": sha or None, "dirty": bool or None}`` of the checkout at ``root`` (default: the one holding
    this package); ``dirty``: the code or the params files differ from the commit (see the module docstring)."""
    cwd = Path(root) if root else _PACKAGE_DIR.parent
    commit = _git("rev-parse", "HEAD", cwd=cwd)
    if commit is None:
        return {"commit": None, "dirty": None}
    top = _git("rev-parse", "--show-toplevel", cwd=cwd)
    paths = [p for p in CODE_PATHS if (Path(top or cwd) / p).exists()]
    status = _git("status", "--porcelain", "--", *paths, cwd=Path(top or cwd)) if paths else ""
    return {"commit": commit, "dirty": bool(status) if status is not None else None}


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


@cache
def machine() -> dict[str, Any]:
    """The CPU model, the cores this process may use, and the GPU when an imported torch sees one."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    out: dict[str, Any] = {"cpu": _cpu_model(), "cores": cores, "gpu": None}
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        out["gpu"] = torch.cuda.get_device_name(0)
    return out


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    return value


def params_hash(params: Any) -> str:
    """16 hex digits of the sha256 of ``params`` (a config dataclass or a mapping) as canonical JSON."""
    text = json.dumps(_plain(params), sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def torch_threads() -> int | None:
    torch = sys.modules.get("torch")
    return torch.get_num_threads() if torch is not None else None


def stamp(params: Any, started: float) -> dict[str, Any]:
    """The ``provenance`` block of a metrics file: ``params`` is the stage's resolved config, ``started`` the
    :func:`time.monotonic` value at the start of the call that writes the file."""
    return {**code_state(), "params_hash": params_hash(params), "torch_threads": torch_threads(),
            "wall_seconds": round(time.monotonic() - started, 1), "machine": machine()}


#: keys of the metrics and state files whose values are wall-clock measurements (or hold them), besides
#: ``seconds`` and every ``*_seconds`` (:func:`is_timing`): they may differ between two runs that give the
#: same numbers
TIMING_KEYS = frozenset({
    "provenance", "shapes_per_second", "seconds_per_shape", "network_seconds_per_shape",
    "refine_seconds_per_shape", "process_seconds_per_shape", "cpu_seconds_per_shape", "stats",
    "wall_seconds_this_call",
    # a pretraining's provenance segments (plad.learn.pretrain): when each started and what it cost
    "started", "cpu_hours", "gpu_hours",
})


def is_timing(key: str) -> bool:
    """Whether a metrics or state file's ``key`` holds a wall-clock measurement."""
    return key in TIMING_KEYS or key == "seconds" or key.endswith("_seconds")


def without_timing(record: Any) -> Any:
    """``record`` (a metrics or state file's JSON) without its wall-clock measurements (:func:`is_timing`), at
    any depth."""
    if isinstance(record, Mapping):
        return {k: without_timing(v) for k, v in record.items() if not is_timing(str(k))}
    if isinstance(record, list):
        return [without_timing(v) for v in record]
    return record
