"""The MLflow model registry: champions, version tags, and model URIs resolved to checkpoint files."""
from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from plad.tracking.store import client, mlflow_module, open_store, tracking_uri

#: the URI schemes of a logged model (``models:/NAME@ALIAS``, ``models:/NAME/VERSION``, ``runs:/RUN/model``)
MODEL_URI_PREFIXES = ("models:/", "runs:/", "mlflow-artifacts:/")


def set_champion(name: str, version: int | str, alias: str = "champion") -> None:
    """Point ``models:/<name>@<alias>`` at ``version``."""
    client().set_registered_model_alias(name, alias, str(version))


def champion_tags(name: str, alias: str = "champion") -> tuple[int, dict[str, str]] | None:
    """(version, tags) of the version ``models:/<name>@<alias>`` points at; ``None`` when there is none."""
    from mlflow.exceptions import MlflowException

    try:
        mv = client().get_model_version_by_alias(name, alias)
    except MlflowException:   # no such registered model, or no such alias
        return None
    return int(mv.version), dict(mv.tags or {})


def set_version_tags(name: str, version: int | str, tags: Mapping[str, Any]) -> None:
    """Tag one registered model version (values as strings)."""
    mlflow_client = client()
    for key, value in tags.items():
        mlflow_client.set_model_version_tag(name, str(version), key, str(value))


def registered_models() -> list[dict[str, Any]]:
    """Every version of every registered model: name, version, aliases and the PLAD tags (method, test metric)."""
    mlflow_client = client()
    rows = []
    for rm in mlflow_client.search_registered_models():
        # search_model_versions leaves ModelVersion.aliases empty on the SQLite store (MLflow 3.17);
        # the registered model carries the alias -> version map.
        by_version: dict[int, list[str]] = {}
        for alias, version in (rm.aliases or {}).items():
            by_version.setdefault(int(version), []).append(alias)
        for mv in mlflow_client.search_model_versions(f"name = '{rm.name}'"):
            rows.append({"name": rm.name, "version": int(mv.version),
                         "aliases": sorted(by_version.get(int(mv.version), [])),
                         "method": (mv.tags or {}).get("plad.method"), "test": (mv.tags or {}).get("plad.test"),
                         "run_id": mv.run_id})
    return sorted(rows, key=lambda r: (r["name"], -r["version"]))


def is_model_uri(ref: str) -> bool:
    return ref.startswith(MODEL_URI_PREFIXES)


def download_checkpoint(uri: str) -> Path:
    """The checkpoint inside a logged PLAD model (its ``checkpoint`` artifact), downloaded to a temporary folder.

    Raises ``LookupError`` (one line, naming the URI and the store) when the
    store does not have the model, ``ValueError`` when the model holds no
    ``.pt`` checkpoint.
    """
    open_store()
    mlflow = mlflow_module()
    from mlflow.exceptions import MlflowException

    dest = Path(tempfile.mkdtemp(prefix="plad-model-"))
    try:
        local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=str(dest)))
    except MlflowException as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else err.__class__.__name__
        raise LookupError(f"{uri}: not found in the MLflow store {tracking_uri()}: {first}") from None
    found = sorted(local.rglob("*.pt")) if local.is_dir() else [local]
    if not found:
        raise ValueError(f"{uri}: a logged model without a PLAD checkpoint")
    return found[0]
