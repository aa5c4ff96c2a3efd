"""MLflow tracking: every pipeline stage execution is one MLflow run.

Usage in a stage::

    with StageRun("pretrain", domain, params, run_dir) as run:
        for step, loss in ...:
            run.log_metrics({"loss": loss}, step=step)
        for r in range(rounds):
            with run.nested(f"round_{r}", round=r):
                run.log_metrics({"val_iou": v}, step=r)     # goes to the child run
        run.log_artifact(metrics_json)
        run.log_model(checkpoint, registered_name=f"plad-{domain}")

Runs of one ``dvc repro`` share the tag ``plad.pipeline`` (see
:func:`pipeline_tags`) so that they can be compared with
``mlflow.search_runs(filter_string="tags.`plad.pipeline` = '...'")``.

The store is ``$MLFLOW_TRACKING_URI`` or ``./mlflow.db`` (SQLite, absolute
path), never the plain ``./mlruns`` file store. For a SQLite store the
experiment's artifacts go beside the database (``<db dir>/mlartifacts/``)
rather than MLflow's default ``<cwd>/mlruns/<id>``, which depends on the
directory the experiment happened to be created from.

``mlflow`` is imported lazily (it costs about 3 s), so ``import plad.tracking``
stays cheap; the pyfunc wrapper class :class:`PladPyfuncModel` is built on
first access for the same reason.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import re
import subprocess
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping

from plad.fsutil import atomic_write_text

RUN_FILE = "mlflow_run.json"
DEFAULT_EXPERIMENT = "plad"
# MLflow's limits (mlflow.utils.validation), repeated here to avoid importing mlflow.
MAX_PARAM_VAL_LENGTH = 6000
MAX_KEY_LENGTH = 250
MAX_TAG_VAL_LENGTH = 8000
_PARAMS_PER_BATCH = 100


# -- where and how runs are grouped ---------------------------------------------------------
def tracking_uri() -> str:
    """``$MLFLOW_TRACKING_URI`` if set, else ``sqlite:///<cwd>/mlflow.db`` (absolute)."""
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if env:
        return env
    return "sqlite:///" + str((Path.cwd() / "mlflow.db").resolve())


def _sqlite_path(uri: str) -> Path | None:
    if not uri.startswith("sqlite:///"):
        return None
    rest = uri[len("sqlite:///"):].split("?", 1)[0]
    if not rest or rest == ":memory:":
        return None
    path = Path(rest)  # sqlite:////abs/path -> "/abs/path"; sqlite:///rel -> relative to the cwd
    return path if path.is_absolute() else path.resolve()


def _git_rev(cwd: Path) -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True,
                             text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "nogit"
    rev = out.stdout.strip()
    return rev if out.returncode == 0 and rev else "nogit"


def pipeline_tags(params_path: str | os.PathLike = "params.yaml") -> dict[str, str]:
    """Tags shared by the runs of one ``dvc repro``.

    ``plad.pipeline``: short hash of the params file bytes and the git revision
    (HEAD of the repository holding the params file, or ``nogit``), or
    ``$PLAD_PIPELINE_ID`` when set; ``plad.git_rev``; ``plad.profile``: the
    params file's top-level ``profile`` value, else ``custom``.
    """
    path = Path(params_path)
    data = path.read_bytes() if path.is_file() else b""
    rev = _git_rev(path.resolve().parent if path.parent.is_dir() else Path.cwd())
    pipeline = os.environ.get("PLAD_PIPELINE_ID") or \
        hashlib.sha256(data + b"\0" + rev.encode()).hexdigest()[:12]
    profile = "custom"
    if data:
        try:
            import yaml

            parsed = yaml.safe_load(data)
        except Exception:  # a broken params file is the config loader's error to report
            parsed = None
        if isinstance(parsed, dict) and parsed.get("profile") is not None:
            profile = str(parsed["profile"])
    return {"plad.pipeline": pipeline, "plad.git_rev": rev, "plad.profile": profile}


# -- params -------------------------------------------------------------------------------
def flatten_params(params: Mapping[str, Any] | Any, prefix: str = "") -> dict[str, str]:
    """Nested dicts (or dataclasses) -> ``{"a.b.c": "value"}`` with MLflow-safe strings.

    Lists and tuples are stringified; values are truncated to MLflow's limit.
    """
    if dataclasses.is_dataclass(params) and not isinstance(params, type):
        params = dataclasses.asdict(params)
    out: dict[str, str] = {}
    for key, value in dict(params).items():
        name = f"{prefix}{key}"
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = dataclasses.asdict(value)
        if isinstance(value, Mapping) and value:
            out.update(flatten_params(value, prefix=name + "."))
            continue
        if isinstance(value, (list, tuple)):
            text = json.dumps(list(value), default=str)
        elif isinstance(value, Mapping):
            text = "{}"
        else:
            text = str(value)
        out[name[:MAX_KEY_LENGTH]] = text[:MAX_PARAM_VAL_LENGTH]
    return out


def _params_hash(flat: Mapping[str, str]) -> str:
    return hashlib.sha256(json.dumps(flat, sort_keys=True).encode()).hexdigest()[:16]


def _tag_values(tags: Mapping[str, Any]) -> dict[str, str]:
    return {str(k)[:MAX_KEY_LENGTH]: str(v)[:MAX_TAG_VAL_LENGTH] for k, v in tags.items()}


# -- mlflow helpers --------------------------------------------------------------------------
def _mlflow():
    """``mlflow`` (imported on first use) pointed at :func:`tracking_uri`."""
    import mlflow

    uri = tracking_uri()
    if mlflow.get_tracking_uri() != uri:
        mlflow.set_tracking_uri(uri)
    return mlflow


def _artifact_location(uri: str, experiment: str) -> str | None:
    """Artifacts of a SQLite store live beside the database, not under the cwd."""
    db = _sqlite_path(uri)
    if db is None:
        return None  # a server or another store decides
    safe = re.sub(r"[^\w.-]+", "_", experiment).strip("._") or "experiment"
    return (db.parent / "mlartifacts" / safe).as_uri()


def _experiment_id(client, uri: str, name: str) -> str:
    from mlflow.exceptions import MlflowException

    exp = client.get_experiment_by_name(name)
    if exp is None:
        try:
            return client.create_experiment(name, artifact_location=_artifact_location(uri, name))
        except MlflowException:  # created concurrently by another stage
            exp = client.get_experiment_by_name(name)
            if exp is None:
                raise
    if exp.lifecycle_stage == "deleted":
        client.restore_experiment(exp.experiment_id)
    return exp.experiment_id


class ChildRun:
    """Handle of a nested run opened by :meth:`StageRun.nested`."""

    def __init__(self, run_id: str):
        self.run_id = run_id

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        _log_metrics(self.run_id, metrics, step)

    def log_params(self, params: Mapping[str, Any]) -> None:
        _log_params(self.run_id, flatten_params(params))

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        _mlflow().MlflowClient().log_batch(self.run_id, tags=_tag_entities(tags))


def _tag_entities(tags: Mapping[str, Any]):
    from mlflow.entities import RunTag

    return [RunTag(k, v) for k, v in _tag_values(tags).items()]


def _log_metrics(run_id: str, metrics: Mapping[str, float], step: int | None) -> None:
    if metrics:
        _mlflow().log_metrics({str(k): float(v) for k, v in metrics.items()}, step=step,
                              run_id=run_id, synchronous=True)


def _log_params(run_id: str, flat: Mapping[str, str]) -> None:
    from mlflow.entities import Param

    client = _mlflow().MlflowClient()
    items = list(flat.items())
    for i in range(0, len(items), _PARAMS_PER_BATCH):
        client.log_batch(run_id, params=[Param(k, v) for k, v in items[i:i + _PARAMS_PER_BATCH]])


# -- one stage execution ---------------------------------------------------------------------
class StageRun:
    """Context manager: one MLflow run per stage execution, resumable after a kill.

    The run id is kept in ``run_dir/mlflow_run.json``. Entering again with the
    same ``run_dir`` resumes that run if it is not FINISHED (a killed training
    re-run continues its run) and was started with the same params, store and
    experiment; otherwise a new run starts. Params are logged only for a new run.
    Exiting ends the run FINISHED, or FAILED (KILLED for KeyboardInterrupt) when
    an exception escapes; exceptions always propagate.
    """

    def __init__(self, stage: str, domain: str, params: Mapping[str, Any] | Any,
                 run_dir: str | os.PathLike, *, method: str | None = None,
                 tags: Mapping[str, Any] | None = None, experiment: str = DEFAULT_EXPERIMENT,
                 params_path: str | os.PathLike = "params.yaml"):
        self.stage = stage
        self.domain = domain
        self.method = method
        self.params = flatten_params(params if params is not None else {})
        self.run_dir = Path(run_dir)
        self.extra_tags = dict(tags or {})
        self.experiment = experiment
        self.params_path = params_path
        self.resumed = False
        self._run_id: str | None = None
        self._tags: dict[str, str] | None = None
        self._stack: list[str] = []          # open runs, innermost last

    # -- state -------------------------------------------------------------------------
    @property
    def run_id(self) -> str:
        if self._run_id is None:
            raise RuntimeError("StageRun.run_id is only known once the run has started")
        return self._run_id

    @property
    def run_file(self) -> Path:
        return self.run_dir / RUN_FILE

    @property
    def tags(self) -> dict[str, str]:
        tags: dict[str, Any] = {"plad.stage": self.stage, "plad.domain": self.domain}
        if self.method:
            tags["plad.method"] = self.method
        tags.update(pipeline_tags(self.params_path))
        tags.update(self.extra_tags)
        return _tag_values(tags)

    def _resumable(self, client, uri: str, experiment_id: str) -> str | None:
        try:
            record = json.loads(self.run_file.read_text())
            run_id = record["run_id"]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if (record.get("tracking_uri"), record.get("experiment_id"), record.get("params_hash")) != \
                (uri, experiment_id, _params_hash(self.params)):
            return None
        try:
            run = client.get_run(run_id)
        except Exception:  # unknown run (store reset): start afresh
            return None
        info = run.info
        if info.status == "FINISHED" or info.lifecycle_stage != "active" \
                or info.experiment_id != experiment_id:
            return None
        return run_id

    # -- context manager --------------------------------------------------------------------
    def __enter__(self) -> "StageRun":
        mlflow = _mlflow()
        uri = tracking_uri()
        client = mlflow.MlflowClient()
        experiment_id = self._exp_id = _experiment_id(client, uri, self.experiment)
        tags = self._tags = self.tags
        previous = self._resumable(client, uri, experiment_id)
        nested = mlflow.active_run() is not None   # e.g. a flow's own run around the stage
        if previous is not None:
            active = mlflow.start_run(run_id=previous, nested=nested)
            self.resumed = True
            client.log_batch(previous, tags=_tag_entities(tags))
        else:
            name = "/".join(x for x in (self.stage, self.method, self.domain) if x)
            active = mlflow.start_run(experiment_id=experiment_id, run_name=name,
                                      nested=nested, tags=tags)
            self.resumed = False
        self._run_id = active.info.run_id
        self._stack = [self._run_id]
        try:
            if not self.resumed:
                _log_params(self._run_id, self.params)
            atomic_write_text(self.run_file, json.dumps({
                "run_id": self._run_id, "experiment_id": experiment_id, "tracking_uri": uri,
                "params_hash": _params_hash(self.params), "stage": self.stage,
                "domain": self.domain, "method": self.method,
            }, indent=2) + "\n")
        except BaseException:
            self._end(mlflow, "FAILED")
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            status = "FINISHED"
        elif issubclass(exc_type, KeyboardInterrupt):
            status = "KILLED"
        else:
            status = "FAILED"
        try:
            self._end(_mlflow(), status)
        except Exception:
            if exc_type is None:
                raise
            warnings.warn(f"could not end MLflow run {self._run_id} as {status}", stacklevel=2)
        return False  # never swallow the exception

    def _end(self, mlflow, status: str) -> None:
        # close anything left open above our run (a leaked child), then our run
        while True:
            active = mlflow.active_run()
            if active is None:
                break
            mlflow.end_run(status)
            if active.info.run_id == self._run_id:
                break
        self._stack = []

    # -- logging ---------------------------------------------------------------------------
    def _current(self) -> str:
        if not self._stack:
            raise RuntimeError("StageRun is not active (use it as a context manager)")
        return self._stack[-1]

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Log to the innermost open run: the stage run, or the child inside :meth:`nested`."""
        _log_metrics(self._current(), metrics, step)

    def log_params(self, params: Mapping[str, Any]) -> None:
        """Extra params on the innermost open run (MLflow params cannot change once logged)."""
        _log_params(self._current(), flatten_params(params))

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        _mlflow().MlflowClient().log_batch(self._current(), tags=_tag_entities(tags))

    def log_artifact(self, path: str | os.PathLike, artifact_path: str | None = None) -> None:
        """A file (or a whole directory) as artifact(s) of the innermost open run."""
        client = _mlflow().MlflowClient()
        path = Path(path)
        if path.is_dir():
            client.log_artifacts(self._current(), str(path), artifact_path)
        else:
            client.log_artifact(self._current(), str(path), artifact_path)

    @contextlib.contextmanager
    def nested(self, name: str, **tags: Any) -> Iterator[ChildRun]:
        """A child run (``mlflow.parentRunId`` = the stage run); metrics logged inside go to it.

        Keyword tags without a dot get the ``plad.`` prefix: ``nested("round_3", round=3)``
        tags the child ``plad.round=3``. The child also carries the stage's
        ``plad.stage/domain/method/pipeline`` tags, so it is found by the same filters.
        """
        mlflow = _mlflow()
        self._current()
        base = {k: v for k, v in (self._tags or self.tags).items()
                if k in ("plad.stage", "plad.domain", "plad.method", "plad.pipeline")}
        extra = {(k if "." in k else f"plad.{k}"): v for k, v in tags.items()}
        # children live in the stage run's experiment (not the fluent API's default one)
        child = mlflow.start_run(nested=True, run_name=name, experiment_id=self._exp_id,
                                 tags=_tag_values({**base, **extra}))
        child_id = child.info.run_id
        self._stack.append(child_id)
        status = "FAILED"
        try:
            yield ChildRun(child_id)
            status = "FINISHED"
        except KeyboardInterrupt:
            status = "KILLED"
            raise
        finally:
            if self._stack and self._stack[-1] == child_id:
                self._stack.pop()
            active = mlflow.active_run()
            if active is not None and active.info.run_id == child_id:
                mlflow.end_run(status)
            else:
                mlflow.MlflowClient().set_terminated(child_id, status)

    # -- models -----------------------------------------------------------------------------
    def log_model(self, checkpoint_path: str | os.PathLike, *, registered_name: str | None = None,
                  beam: int = 10) -> str:
        """Log the checkpoint as a pyfunc model (artifact path ``model``) of the innermost run.

        Returns ``models:/<name>/<version>`` when ``registered_name`` is given
        (the model is registered under it), else the logged model's URI.
        """
        mlflow = _mlflow()
        from mlflow.models import ModelSignature
        from mlflow.types import ParamSchema, ParamSpec

        current = self._current()
        active = mlflow.active_run()
        if active is None or active.info.run_id != current:
            raise RuntimeError("log_model must be called from the thread that entered the StageRun")
        checkpoint_path = Path(checkpoint_path)
        if not checkpoint_path.is_file():
            raise FileNotFoundError(f"{checkpoint_path}: no such checkpoint")
        # a params-only signature: without it MLflow drops predict(params=...) with a warning
        signature = ModelSignature(inputs=None, outputs=None,
                                   params=ParamSchema([ParamSpec("beam", "long", int(beam))]))
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*input example.*")
            info = mlflow.pyfunc.log_model(
                name="model",
                python_model=_pyfunc_class()(beam=beam),
                artifacts={"checkpoint": str(checkpoint_path)},
                pip_requirements=pip_requirements(),
                signature=signature,
                registered_model_name=registered_name,
            )
        if registered_name:
            return f"models:/{registered_name}/{info.registered_model_version}"
        return info.model_uri


def pip_requirements() -> list[str]:
    """Requirements of the logged pyfunc model (no environment capture: offline-safe)."""
    from plad import __version__

    return ["torch", "numpy", "pandas", f"plad=={__version__}"]


# -- registry -----------------------------------------------------------------------------------
def set_champion(name: str, version: int | str, alias: str = "champion") -> None:
    """Point ``models:/<name>@<alias>`` at ``version``."""
    _mlflow().MlflowClient().set_registered_model_alias(name, alias, str(version))


def registered_models() -> list[dict[str, Any]]:
    """Every version of every registered model: name, version, aliases and the PLAD tags (method, test metric)."""
    client = _mlflow().MlflowClient()
    rows = []
    for rm in client.search_registered_models():
        # search_model_versions leaves ModelVersion.aliases empty on the SQLite store (MLflow 3.17);
        # the registered model carries the alias -> version map.
        by_version: dict[int, list[str]] = {}
        for alias, version in (rm.aliases or {}).items():
            by_version.setdefault(int(version), []).append(alias)
        for mv in client.search_model_versions(f"name = '{rm.name}'"):
            rows.append({"name": rm.name, "version": int(mv.version), "aliases": sorted(by_version.get(int(mv.version), [])),
                         "method": (mv.tags or {}).get("plad.method"), "test": (mv.tags or {}).get("plad.test"),
                         "run_id": mv.run_id})
    return sorted(rows, key=lambda r: (r["name"], -r["version"]))


def load_registered(uri: str):
    """The pyfunc model at ``uri`` (``models:/name@champion``, ``models:/name/3``, ...)."""
    return _mlflow().pyfunc.load_model(uri)


# -- the pyfunc wrapper ----------------------------------------------------------------------------
def _stack_input(model_input: Any, shape: tuple[int, ...]):
    """(N, *shape) bool numpy array from an ndarray, a list of arrays or a DataFrame."""
    import numpy as np

    if hasattr(model_input, "columns") and hasattr(model_input, "to_numpy"):   # DataFrame
        frame = model_input
        if frame.shape[1] == 1:
            cells = list(frame.iloc[:, 0])
            model_input = np.stack([np.asarray(c) for c in cells]) if cells else \
                np.zeros((0, *shape), bool)
        else:  # one flattened shape per row
            model_input = frame.to_numpy().reshape(len(frame), *shape)
    elif isinstance(model_input, dict) and len(model_input) == 1:
        model_input = next(iter(model_input.values()))
    arr = np.asarray(model_input)
    if arr.dtype == object:
        arr = np.stack([np.asarray(a) for a in arr])
    if arr.shape == tuple(shape):
        arr = arr[None]
    if arr.shape[1:] != tuple(shape):
        raise ValueError(f"expected shapes of size {tuple(shape)}, got an array of shape {arr.shape}")
    return arr.astype(bool)


def _build_pyfunc_class():
    import mlflow.pyfunc
    import numpy as np

    def load_context(self, context):
        import torch

        from plad.checkpoint import load_model
        from plad.domains import get_domain

        device = "cuda" if torch.cuda.is_available() else "cpu"
        self.model, name = load_model(context.artifacts["checkpoint"], device)
        self.domain = get_domain(name)

    def predict(self, context, model_input, params=None):
        import pandas as pd
        import torch

        from plad.search import infer_programs

        beam = int((params or {}).get("beam") or self.beam)
        arr = _stack_input(model_input, tuple(self.domain.shape))
        device = next(self.model.parameters()).device
        programs: list[str] = []
        values: list[float] = []
        for i in range(0, len(arr), self.batch_size):
            targets = torch.from_numpy(arr[i:i + self.batch_size]).to(device)
            result = infer_programs(self.model, self.domain, targets, beam)
            programs += [self.domain.format(p) for p in result.programs]
            values += result.values.double().cpu().tolist()
        return pd.DataFrame({"program": programs, self.domain.metric.name: values})

    # An ndarray hint tells MLflow not to infer a schema from the hints (the input is
    # passed through untouched; DataFrames work too). Without any hint MLflow warns
    # at class creation, from inside its own ``simplefilter("once")``: unfilterable.
    predict.__annotations__ = {"model_input": np.ndarray}

    def __init__(self, beam: int = 10):
        self.beam = int(beam)
        self.model = None
        self.domain = None

    namespace = {
        "__module__": __name__,
        "__qualname__": "PladPyfuncModel",
        "__doc__": """Shapes in, programs out: best-of-beam inference with a PLAD checkpoint.

        ``predict(context, model_input, params=None)``: ``model_input`` is a
        bool/uint8 array (N, *shape) (or a one-column DataFrame of such
        arrays); returns a DataFrame with columns ``program`` (text) and the
        domain metric's name. ``params={"beam": k}`` overrides the beam width.
        """,
        "batch_size": 64,
        "__init__": __init__,
        "load_context": load_context,
        "predict": predict,
    }
    return type("PladPyfuncModel", (mlflow.pyfunc.PythonModel,), namespace)


def _pyfunc_class():
    cls = globals().get("PladPyfuncModel")
    if cls is None:
        cls = _build_pyfunc_class()
        globals()["PladPyfuncModel"] = cls
    return cls


def __getattr__(name: str):
    # ``plad.tracking.PladPyfuncModel`` is built on first access (it subclasses an
    # mlflow class), which is also how a pickled instance finds it when loaded.
    if name == "PladPyfuncModel":
        return _pyfunc_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["ChildRun", "PladPyfuncModel", "StageRun", "flatten_params", "load_registered",
           "pip_requirements", "pipeline_tags", "set_champion", "tracking_uri"]
