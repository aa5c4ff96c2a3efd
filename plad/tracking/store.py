"""Where the MLflow store is, and the one place that imports ``mlflow``.

The store is ``$MLFLOW_TRACKING_URI`` or ``./mlflow.db`` (SQLite, absolute
path), never the plain ``./mlruns`` file store. For a SQLite store the
experiment's artifacts go beside the database (``<db dir>/mlartifacts/``)
rather than MLflow's default ``<cwd>/mlruns/<id>``, which depends on the
directory the experiment happened to be created from.

``mlflow`` is imported lazily by :func:`mlflow_module` (it costs about 3 s),
so importing :mod:`plad.tracking` stays cheap.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

DEFAULT_EXPERIMENT = "plad"
# MLflow's limits (mlflow.utils.validation), repeated here to avoid importing mlflow.
MAX_PARAM_VAL_LENGTH = 6000
MAX_KEY_LENGTH = 250
MAX_TAG_VAL_LENGTH = 8000


def tracking_uri() -> str:
    """``$MLFLOW_TRACKING_URI`` if set, else ``sqlite:///<cwd>/mlflow.db`` (absolute)."""
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if env:
        return env
    return "sqlite:///" + str((Path.cwd() / "mlflow.db").resolve())


def mlflow_module() -> Any:
    """``mlflow`` (imported on first use) pointed at :func:`tracking_uri`."""
    import mlflow

    uri = tracking_uri()
    if mlflow.get_tracking_uri() != uri:
        mlflow.set_tracking_uri(uri)
    return mlflow


def client() -> Any:
    """An ``MlflowClient`` of the store at :func:`tracking_uri`."""
    return mlflow_module().MlflowClient()


def sqlite_path(uri: str) -> Path | None:
    """The database file of a SQLite store URI (absolute), else ``None``."""
    if not uri.startswith("sqlite:///"):
        return None
    rest = uri[len("sqlite:///"):].split("?", 1)[0]
    if not rest or rest == ":memory:":
        return None
    path = Path(rest)  # sqlite:////abs/path -> "/abs/path"; sqlite:///rel -> relative to the cwd
    return path if path.is_absolute() else path.resolve()


def _artifact_location(uri: str, experiment: str) -> str | None:
    """Artifacts of a SQLite store live beside the database, not under the cwd."""
    db = sqlite_path(uri)
    if db is None:
        return None  # a server or another store decides
    safe = re.sub(r"[^\w.-]+", "_", experiment).strip("._") or "experiment"
    return (db.parent / "mlartifacts" / safe).as_uri()


def ensure_experiment(mlflow_client: Any, uri: str, name: str) -> str:
    """The id of experiment ``name``, created (or restored from deleted) when needed."""
    from mlflow.exceptions import MlflowException

    exp = mlflow_client.get_experiment_by_name(name)
    if exp is None:
        try:
            return mlflow_client.create_experiment(name, artifact_location=_artifact_location(uri, name))
        except MlflowException:  # created concurrently by another stage
            exp = mlflow_client.get_experiment_by_name(name)
            if exp is None:
                raise
    if exp.lifecycle_stage == "deleted":
        mlflow_client.restore_experiment(exp.experiment_id)
    return exp.experiment_id


def find_experiment(name: str = DEFAULT_EXPERIMENT) -> str:
    """The id of an existing experiment; ``LookupError`` naming the store when there is none."""
    exp = client().get_experiment_by_name(name)
    if exp is None:
        raise LookupError(f"no MLflow experiment {name!r} at {tracking_uri()}")
    return exp.experiment_id
