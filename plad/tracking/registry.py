"""The MLflow model registry: champions, version tags, and model URIs resolved to checkpoint files.

Which test set a model was measured on decides whether it may become a default. Every stage run carries the
tag ``plad.test_set`` (:func:`plad.tracking.runs.pipeline_tags`): ``full`` when its params evaluate every
domain on all of its real test shapes, ``subset`` when they evaluate a few (the ``smoke`` profile), ``unknown``
when the params file could not be read. A model registered by a ``subset`` run lives under a name of its
own, ``<name>-<profile>`` (e.g. ``plad-<domain>-smoke``; :func:`model_name`), with its own ``champion`` alias, so
that a trial never moves ``plad-<domain>@champion``; every version carries its run's ``plad.profile`` and
``plad.test_set`` tags (:func:`tag_version_with_run`), and :func:`evaluated_on` reads them back
(``plad infer`` takes a champion only when it says ``full``: :mod:`plad.serve.resolve`).
"""
from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from plad.tracking.store import client, mlflow_module, open_store, tracking_uri

#: the URI schemes of a logged model (``models:/NAME@ALIAS``, ``models:/NAME/VERSION``, ``runs:/RUN/model``)
MODEL_URI_PREFIXES = ("models:/", "runs:/", "mlflow-artifacts:/")

#: the tags of a run (and of the model versions it registers): its profile, and the test set its params evaluate
PROFILE_TAG = "plad.profile"
TEST_SET_TAG = "plad.test_set"
FULL, SUBSET, UNKNOWN = "full", "subset", "unknown"
#: the profiles that evaluate every test shape, for versions registered before :data:`TEST_SET_TAG` existed
FULL_PROFILES = ("cpu", "paper")


def evaluated_on(tags: Mapping[str, str]) -> str:
    """:data:`FULL`, :data:`SUBSET` or :data:`UNKNOWN`: the test set of the run (or model version) with these tags.

    A version registered before :data:`TEST_SET_TAG` existed is judged by its profile: ``cpu`` and ``paper``
    evaluate every test shape, any other (``smoke``: a few) is not known to."""
    value = tags.get(TEST_SET_TAG)
    if value in (FULL, SUBSET, UNKNOWN):
        return value
    return FULL if tags.get(PROFILE_TAG) in FULL_PROFILES else UNKNOWN


def _active_run_tags() -> dict[str, str]:
    """The tags of the active MLflow run (read from the store), or {} outside a run."""
    mlflow = mlflow_module()
    active = mlflow.active_run()
    if active is None:
        return {}
    return dict(client().get_run(active.info.run_id).data.tags)


def model_name(name: str, run_tags: Mapping[str, str] | None = None) -> str:
    """The registered model name ``name`` stands for in the active run (or the run with ``run_tags``).

    ``name`` itself, unless the run's params evaluate a subset of the test set (:data:`SUBSET`, e.g. the
    ``smoke`` profile): then ``<name>-<profile>``, so that a trial's models, and its champion, never take the
    place of the real ones (``plad-<domain>@champion``, which ``plad infer`` uses)."""
    tags = _active_run_tags() if run_tags is None else run_tags
    if tags.get(TEST_SET_TAG) != SUBSET:
        return name
    suffix = f"-{tags.get(PROFILE_TAG) or SUBSET}"
    return name if name.endswith(suffix) else name + suffix


def tag_version_with_run(name: str, version: int | str, run_tags: Mapping[str, str]) -> None:
    """Copy the run's :data:`PROFILE_TAG` and :data:`TEST_SET_TAG` onto a model version it registered."""
    set_version_tags(name, version, {k: run_tags[k] for k in (PROFILE_TAG, TEST_SET_TAG) if k in run_tags},
                     rename=False)


def set_champion(name: str, version: int | str, alias: str = "champion") -> None:
    """Point ``models:/<name>@<alias>`` at ``version`` (``name`` as :func:`model_name` maps it in a run)."""
    client().set_registered_model_alias(model_name(name), alias, str(version))


def champion_tags(name: str, alias: str = "champion") -> tuple[int, dict[str, str]] | None:
    """(version, tags) of the version ``models:/<name>@<alias>`` points at (``name`` as :func:`model_name` maps
    it in a run); ``None`` when there is none."""
    from mlflow.exceptions import MlflowException

    try:
        mv = client().get_model_version_by_alias(model_name(name), alias)
    except MlflowException:   # no such registered model, or no such alias
        return None
    return int(mv.version), dict(mv.tags or {})


def champion_record(name: str, alias: str = "champion") -> tuple[int, dict[str, str]] | None:
    """(version, tags) of ``models:/<name>@<alias>`` exactly as named, its run's tags under the version's own
    (what :func:`evaluated_on` reads; a version registered before the versions carried them has them on its
    run); ``None`` when there is none. A store that cannot be opened is a
    :class:`plad.tracking.store.StoreError`."""
    from mlflow.exceptions import MlflowException

    mlflow_client = client()
    try:
        mv = mlflow_client.get_model_version_by_alias(name, alias)
    except MlflowException:   # no such registered model, or no such alias
        return None
    tags: dict[str, str] = {}
    if mv.run_id:
        try:
            tags.update(mlflow_client.get_run(mv.run_id).data.tags)
        except MlflowException:   # the run was deleted: the version's own tags only
            pass
    tags.update(mv.tags or {})
    return int(mv.version), tags


def set_version_tags(name: str, version: int | str, tags: Mapping[str, Any], *, rename: bool = True) -> None:
    """Tag one registered model version (values as strings); ``name`` as :func:`model_name` maps it in a run,
    unless not ``rename``."""
    mlflow_client = client()
    name = model_name(name) if rename else name
    for key, value in tags.items():
        mlflow_client.set_model_version_tag(name, str(version), key, str(value))


def registered_models() -> list[dict[str, Any]]:
    """Every version of every registered model: name, version, aliases and the PLAD tags (method, test metric,
    profile and test set: None on versions registered before they were tagged)."""
    mlflow_client = client()
    rows = []
    for rm in mlflow_client.search_registered_models():
        # search_model_versions leaves ModelVersion.aliases empty on the SQLite store (MLflow 3.17);
        # the registered model carries the alias -> version map.
        by_version: dict[int, list[str]] = {}
        for alias, version in (rm.aliases or {}).items():
            by_version.setdefault(int(version), []).append(alias)
        for mv in mlflow_client.search_model_versions(f"name = '{rm.name}'"):
            tags = mv.tags or {}
            rows.append({"name": rm.name, "version": int(mv.version),
                         "aliases": sorted(by_version.get(int(mv.version), [])),
                         "method": tags.get("plad.method"), "test": tags.get("plad.test"),
                         "profile": tags.get(PROFILE_TAG), "test_set": tags.get(TEST_SET_TAG),
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
