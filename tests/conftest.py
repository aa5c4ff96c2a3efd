"""Shared test set-up: the environment, the shared folder (skip or fail), the fixtures every folder uses,
the markers that pick what a run selects.

The reference fixtures and real datasets live outside the repository in
``../shared`` (override with ``PLAD_SHARED_DIR``). Where that folder is
absent, tests that need it skip with a reason; under CI (``CI=true``) they
fail instead, so a wrong path can never hide a regression.

Markers (tests/README.md): ``pipeline`` (runs whole stage pipelines) and ``integration`` (starts real
processes) are left out of the default run (pyproject's addopts); every other test is marked ``unit``
here, so that ``-m "unit or pipeline or integration"`` (the README's CI command) is the whole suite.
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


# The stages and CLIs the tests run read the data directory from params (null: $PLAD_DATA_DIR, else
# ./data/datasets, which a fresh clone lacks): point them at the shared datasets the tests read themselves, so
# the README's test command needs no environment variable
if "PLAD_DATA_DIR" not in os.environ and (shared_dir() / "datasets").is_dir():
    os.environ["PLAD_DATA_DIR"] = str(shared_dir() / "datasets")


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


# -- fixtures --------------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    """The reference fixtures (``../shared/fixtures``); skip (or fail under CI) when missing."""
    return require_shared("fixtures")


@pytest.fixture(scope="session")
def tiny_model():
    """The factory of the tests' tiny, untrained network: ``tiny_model(domain="csg2d", seed=0, **knobs)``
    (:func:`tests.tiny.tiny_model`)."""
    from tests.tiny import tiny_model

    return tiny_model


@pytest.fixture(scope="session")
def tiny_checkpoint():
    """The factory of the tiny network's checkpoints: ``tiny_checkpoint(path, domain="csg2d", seed=0)`` -> path
    (:func:`tests.tiny.tiny_checkpoint`)."""
    from tests.tiny import tiny_checkpoint

    return tiny_checkpoint


@pytest.fixture
def tmp_layout(tmp_path):
    """A :class:`plad.layout.Layout` rooted at a fresh temporary folder (nothing written yet)."""
    from plad.layout import Layout

    return Layout(tmp_path / "root")


@pytest.fixture(scope="module")
def csg2d_project(tmp_path_factory, datasets_dir) -> Path:
    """A layout root, one per test module, ready to fine-tune 2D CSG: the real shapes prepared and the tiny
    model as the pretrained one (:func:`tests.tiny.csg2d_inputs`)."""
    from tests.tiny import csg2d_inputs

    return csg2d_inputs(tmp_path_factory.mktemp("csg2d-project"), datasets_dir)


# -- what a run selects and how it is spread over workers -------------------------------------------


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    """``-n N`` distributes whole files (``--dist loadfile``: a module fixture such as the smoke pipeline runs
    once) in the order below, unless the command line names another ``--dist``."""
    if getattr(config.option, "numprocesses", None) and config.option.dist == "no":
        config.option.dist = "loadfile"
        config.option.loadscopereorder = False


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Mark every test that is neither ``pipeline``, ``integration`` nor ``slow`` as ``unit`` (before ``-m`` selects),
    and put files marked ``slow_first`` first, so that under ``-n 2`` one worker runs the long smoke pipeline
    while the other runs everything else (stable order otherwise)."""
    for item in items:
        if not any(item.get_closest_marker(m) for m in ("pipeline", "integration", "slow")):
            item.add_marker(pytest.mark.unit)
    items.sort(key=lambda item: 0 if item.get_closest_marker("slow_first") else 1)
