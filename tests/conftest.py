"""Shared test helpers: where ../shared lives, and skip-or-fail for its files.

The reference fixtures and real datasets live outside the repository in
``../shared`` (override with ``PLAD_SHARED_DIR``). Where that folder is
absent, tests that need it skip with a reason; under CI (``CI=true``) they
fail instead, so a wrong path can never hide a regression.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent

# Keep Prefect's and DVC's state out of the user's home and quiet offline.
os.environ.setdefault("PREFECT_HOME", str(REPO_ROOT / ".prefect"))
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("DVC_NO_ANALYTICS", "1")
# Under pytest-xdist the workers share the machine's cores: one intra-op thread per worker (and
# per stage subprocess it starts, through the environment) instead of each worker oversubscribing
# every core, which made the two-worker run slower than the sum of its halves suggests.
# (torch is not imported before this file, so the environment is enough.)
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
# Stage runs in tests must never write into the developer's own MLflow store.
os.environ.setdefault("MLFLOW_TRACKING_URI",
                      f"sqlite:///{tempfile.mkdtemp(prefix='plad-test-mlflow-')}/mlflow.db")


def shared_dir() -> Path:
    return Path(os.environ.get("PLAD_SHARED_DIR", REPO_ROOT.parent / "shared")).resolve()


def under_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_shared(relative: str) -> Path:
    """Path of a file under ../shared; skip (or fail under CI) when missing."""
    path = shared_dir() / relative
    if not path.exists():
        message = f"{path} is missing (set PLAD_SHARED_DIR to the shared folder)"
        if under_ci():
            pytest.fail(f"CI=true and {message}")
        pytest.skip(message)
    return path


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """The real-data directory the tests use: $PLAD_DATA_DIR or ../shared/datasets."""
    env = os.environ.get("PLAD_DATA_DIR")
    if env:
        path = Path(env)
        if not path.exists():
            pytest.fail(f"PLAD_DATA_DIR={env} does not exist")
        return path
    return require_shared("datasets")


def pytest_collection_modifyitems(config, items):
    """Put files marked ``slow_first`` first, so that under ``-n 2 --dist loadfile`` one worker runs
    the long smoke pipeline while the other runs everything else (stable order otherwise)."""
    items.sort(key=lambda item: 0 if item.get_closest_marker("slow_first") else 1)
