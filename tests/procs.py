"""Processes that integration tests start: each in a process group of its own, always stopped by the test.

A test (or its fixture finalizer) calls :func:`stop` on everything it started,
also when it fails; :func:`new_children` then checks that nothing is left.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import psutil

REPO_ROOT = Path(__file__).resolve().parent.parent
#: process groups started through :func:`start` (a group's id is its leader's pid)
STARTED: set[int] = set()
#: the torchrun entry point of :func:`launch`, run as a module (torchrun -m): as a script, its folder tests/
#: would come first on sys.path, where tests/plad/ would shadow the package plad
WORKER = "tests.distributed_worker"


def child_env(**extra: str) -> dict[str, str]:
    """This environment with the repository importable, one torch thread, quiet offline tools, and ``extra``."""
    env = dict(os.environ)
    env.update(PYTHONPATH=os.pathsep.join(p for p in (str(REPO_ROOT), env.get("PYTHONPATH")) if p),
               OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", DO_NOT_TRACK="1", DVC_NO_ANALYTICS="1",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PYTHONUNBUFFERED="1")
    env.update(extra)
    return env


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(cmd: list[str], env: dict[str, str], log: Path, cwd: Path | None = None) -> subprocess.Popen:
    """Start ``cmd`` in a new session (its own process group), output to ``log``."""
    with open(log, "ab") as fh:
        proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    STARTED.add(proc.pid)
    return proc


def stop(proc: subprocess.Popen, grace: float = 10.0) -> None:
    """Stop ``proc`` and every process of its group: SIGTERM, SIGKILL to what is left after ``grace`` seconds
    (or once the leader is gone: e.g. multiprocessing's resource tracker ignores SIGTERM), and wait until the
    group is empty."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        pass
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()
    deadline = time.monotonic() + 10
    while group(proc.pid) and time.monotonic() < deadline:   # SIGKILL is delivered, not yet done
        time.sleep(0.05)


def run(cmd: list[str], env: dict[str, str], log: Path, timeout: float, cwd: Path | None = None) -> int:
    """Run ``cmd`` to completion (its group is stopped on timeout or error); its exit status."""
    proc = start(cmd, env, log, cwd)
    try:
        return proc.wait(timeout=timeout)
    finally:
        stop(proc)


def tail(log: Path, lines: int = 40) -> str:
    return "\n".join(log.read_text(errors="replace").splitlines()[-lines:]) if log.exists() else "(no log)"


def wait_http(url: str, proc: subprocess.Popen, log: Path, timeout: float) -> None:
    """Wait until ``url`` answers 200; fail early if ``proc`` exits."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"{proc.args[0]} exited with {proc.returncode}:\n{tail(log)}")
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    raise TimeoutError(f"{url} did not answer within {timeout:.0f} s:\n{tail(log)}")


def children() -> set[int]:
    return {p.pid for p in psutil.Process().children(recursive=True)}


def describe(p: psutil.Process) -> str:
    return f"pid {p.pid} (parent {p.ppid()}, group {os.getpgid(p.pid)}): {' '.join(p.cmdline())[:120]}"


def group(leader: int) -> list[str]:
    """Live processes of the process group of ``leader`` (also those whose parent died): pid and command."""
    out = []
    for p in psutil.process_iter():
        try:
            if os.getpgid(p.pid) == leader and p.status() != psutil.STATUS_ZOMBIE:
                out.append(describe(p))
        except (psutil.NoSuchProcess, ProcessLookupError):
            pass
    return out


def left_behind(before: set[int]) -> list[str]:
    """Live processes a test left: children of this process that were not there ``before``, and the
    members of every group :func:`start` created since (leaders not in ``before``). Pid and command."""
    out = []
    for p in psutil.Process().children(recursive=True):
        try:
            if p.pid not in before and p.status() != psutil.STATUS_ZOMBIE:
                out.append(describe(p))
        except psutil.NoSuchProcess:
            pass
    for leader in STARTED - before:
        out += [m for m in group(leader) if m not in out]
    return out


def launch(tmp: Path, name: str, commands: list[list[str]]) -> list[list[dict]]:
    """One ``torchrun --nproc-per-node 2`` running the stage commands in turn (in ``tmp``, MLflow store
    ``tmp/mlflow.db``; :data:`WORKER` records each rank's steps and writes); per command, the records of
    rank 0 and rank 1."""
    records = tmp / f"records-{name}"
    records.mkdir()
    log = tmp / f"{name}.log"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", WORKER, str(records), *" :: ".join(" ".join(c) for c in commands).split(" ")]
    env = child_env(PLAD_TEST_WATCH=str(tmp), MLFLOW_TRACKING_URI=f"sqlite:///{tmp / 'mlflow.db'}")
    status = run(cmd, env, log, timeout=300, cwd=tmp)
    assert status == 0, tail(log)
    ranks = [json.loads((records / f"rank{r}.json").read_text()) for r in (0, 1)]
    return [list(pair) for pair in zip(*ranks)]
