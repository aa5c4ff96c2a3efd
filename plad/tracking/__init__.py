"""MLflow tracking: every pipeline stage execution is one MLflow run; the registry; pyfunc serving.

The only package that talks to MLflow (``mlflow`` itself is imported lazily,
so ``import plad.tracking`` stays cheap):

* :mod:`plad.tracking.store`: where the store is (``$MLFLOW_TRACKING_URI`` or
  ``./mlflow.db``), opening it (:func:`open_store`: a new SQLite store created once under a lock,
  a broken one a one-line :class:`StoreError`) and the experiments: ``plad-<domain>`` per domain
  (:func:`domain_experiment`), ``plad`` for the pipeline runs (:data:`PIPELINE_EXPERIMENT`);
* :mod:`plad.tracking.runs`: :class:`StageRun`, one run per stage execution
  (resumable, nested child runs per round), and reading finished runs back;
* :mod:`plad.tracking.rows`: a domain experiment's top level, one run per method
  with its stage runs nested under it, and the experiments' kind, description and
  saved results view;
* :mod:`plad.tracking.registry`: champions, version tags, model URIs
  resolved to checkpoint files;
* :mod:`plad.tracking.serving`: a checkpoint as a pyfunc model, logged as MLflow
  "models from code" (``plad/tracking/pyfunc_model.py``) and loaded (:func:`plad.serve.resolve.load_pyfunc` loads
  the one ``plad infer`` would use: ``--model``, the configured store's champion, the shipped one).
"""
from __future__ import annotations

from typing import Any

from plad.tracking.readback import RunRecord, latest_finished_run, metric_history
from plad.tracking.registry import (
    champion_tags,
    download_checkpoint,
    is_model_uri,
    registered_models,
    set_champion,
    set_version_tags,
)
from plad.tracking.runs import RUN_FILE, ChildRun, StageRun, flatten_params, pipeline_tags
from plad.tracking.serving import legacy_pyfunc_class, load_checkpoint_pyfunc, load_registered, pip_requirements
from plad.tracking.store import (
    PIPELINE_EXPERIMENT,
    StoreError,
    domain_experiment,
    find_experiment,
    find_experiments,
    open_store,
    tracking_uri,
)


def __getattr__(name: str) -> Any:
    # ``plad.tracking.PladPyfuncModel``: the class of the models logged as pickles before models from
    # code, found by this name when one is loaded; built on first access (it subclasses an mlflow class)
    if name == "PladPyfuncModel":
        return legacy_pyfunc_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["PIPELINE_EXPERIMENT", "RUN_FILE", "ChildRun", "PladPyfuncModel", "RunRecord", "StageRun", "StoreError",
           "champion_tags", "domain_experiment", "download_checkpoint", "find_experiment", "find_experiments",
           "flatten_params", "is_model_uri",
           "latest_finished_run", "legacy_pyfunc_class", "load_checkpoint_pyfunc", "load_registered",
           "metric_history", "open_store", "pip_requirements", "pipeline_tags", "registered_models", "set_champion",
           "set_version_tags", "tracking_uri"]
