"""One MLflow run per pipeline stage execution (:class:`StageRun`), and reading runs back.

Runs of one ``dvc repro`` share the tag ``plad.pipeline`` (see
:func:`pipeline_tags`) so that they can be compared with
``mlflow.search_runs(filter_string="tags.`plad.pipeline` = '...'")``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import yaml

from plad.config import load_params, profile_path
from plad.fsutil import atomic_write_text
from plad.layout import SP
from plad.provenance import code_state, params_hash

# reading runs back: plad.tracking.readback (its names stay importable from here)
from plad.tracking.readback import RunRecord as RunRecord
from plad.tracking.readback import latest_finished_run as latest_finished_run
from plad.tracking.readback import metric_history as metric_history
from plad.tracking.registry import FULL, SUBSET, TEST_SET_TAG, UNKNOWN, model_name, tag_version_with_run
from plad.tracking.rows import (
    PIPELINE,
    RESULT,
    Row,
    describe_domain,
    log_result,
    mark_training_experiment,
    row_run,
    set_row_status,
)
from plad.tracking.serving import log_pyfunc
from plad.tracking.store import (
    MAX_KEY_LENGTH,
    MAX_PARAM_VAL_LENGTH,
    MAX_TAG_VAL_LENGTH,
    PIPELINE_EXPERIMENT,
    client,
    domain_experiment,
    ensure_experiment,
    mlflow_module,
    open_store,
    store_errors,
)

RUN_FILE = "mlflow_run.json"
_PARAMS_PER_BATCH = 100


# -- how runs are grouped -------------------------------------------------------------------
def pipeline_tags(params_path: str | os.PathLike = "params.yaml") -> dict[str, str]:
    """Tags shared by the runs of one ``dvc repro``.

    ``plad.pipeline``: short hash of the params file bytes, those of its
    profile's override file (:func:`plad.config.profile_path`) and the git
    revision (HEAD of the repository holding the params file, or ``nogit``),
    or ``$PLAD_PIPELINE_ID`` when set; ``plad.git_rev``; ``plad.profile``:
    the params file's top-level ``profile`` value, else ``custom``; ``plad.test_set``: ``full`` when the
    params (profile applied) evaluate every domain on all of its real test shapes, ``subset`` when they
    limit them (``prepare.limit``, an ``evaluate`` block's ``limit``: the smoke profile), ``unknown`` when
    the params file cannot be read (:func:`evaluated_test_set`; a model a ``subset`` run registers lives under a
    name of its own: :func:`plad.tracking.registry.model_name`).
    """
    path = Path(params_path)
    data = path.read_bytes() if path.is_file() else b""
    rev = code_state(str(path.resolve().parent if path.parent.is_dir() else Path.cwd()))["commit"] or "nogit"
    profile = "custom"
    if data:
        try:
            parsed = yaml.safe_load(data)
        except Exception:  # a broken params file is the config loader's error to report
            parsed = None
        if isinstance(parsed, dict) and parsed.get("profile") is not None:
            profile = str(parsed["profile"])
    overrides = profile_path(path, profile)
    if profile != "custom" and overrides.is_file():
        data += b"\0" + overrides.read_bytes()
    pipeline = os.environ.get("PLAD_PIPELINE_ID") or \
        hashlib.sha256(data + b"\0" + rev.encode()).hexdigest()[:12]
    return {"plad.pipeline": pipeline, "plad.git_rev": rev, "plad.profile": profile,
            TEST_SET_TAG: evaluated_test_set(path)}


def evaluated_test_set(params_path: str | os.PathLike) -> str:
    """Which test shapes the params file (its profile applied) evaluates: ``full`` (all of every domain's),
    ``subset`` (a limit on the prepared data or on an evaluation: the smoke profile) or ``unknown`` (the file
    is missing or cannot be resolved)."""
    try:
        params = load_params(params_path)
    except Exception:  # a missing or broken params file is the config loader's error to report, not a tag's
        return UNKNOWN
    prepare = params.get("prepare") or {}
    limits = list((prepare.get("limit") or {}).values()) if isinstance(prepare.get("limit"), dict) else \
        [prepare.get("limit")]
    limits += [block.get("limit") for block in (params.get("evaluate") or {}).values() if isinstance(block, dict)]
    return SUBSET if any(limit is not None for limit in limits) else FULL


# -- params ---------------------------------------------------------------------------------
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


def _tag_values(tags: Mapping[str, Any]) -> dict[str, str]:
    return {str(k)[:MAX_KEY_LENGTH]: str(v)[:MAX_TAG_VAL_LENGTH] for k, v in tags.items()}


# -- logging to a run by id -------------------------------------------------------------------
def _tag_entities(tags: Mapping[str, Any]) -> list[Any]:
    from mlflow.entities import RunTag

    return [RunTag(k, v) for k, v in _tag_values(tags).items()]


def _log_metrics(run_id: str, metrics: Mapping[str, float], step: int | None) -> None:
    if metrics:
        mlflow_module().log_metrics({str(k): float(v) for k, v in metrics.items()}, step=step,
                                    run_id=run_id, synchronous=True)


def _log_params(run_id: str, flat: Mapping[str, str]) -> None:
    from mlflow.entities import Param

    mlflow_client = client()
    items = list(flat.items())
    for i in range(0, len(items), _PARAMS_PER_BATCH):
        mlflow_client.log_batch(run_id, params=[Param(k, v) for k, v in items[i:i + _PARAMS_PER_BATCH]])


def _set_tags(run_id: str, tags: Mapping[str, Any]) -> None:
    client().log_batch(run_id, tags=_tag_entities(tags))


class ChildRun:
    """Handle of a nested run opened by :meth:`StageRun.nested`."""

    def __init__(self, run_id: str):
        self.run_id = run_id

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        _log_metrics(self.run_id, metrics, step)

    def log_params(self, params: Mapping[str, Any]) -> None:
        _log_params(self.run_id, flatten_params(params))

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        _set_tags(self.run_id, tags)


# -- one stage execution ------------------------------------------------------------------------
class StageRun:
    """Context manager: one MLflow run per stage execution, resumable after a kill.

    Usage in a stage::

        with StageRun("pretrain", domain, params, run_dir) as run:
            for step, loss in ...:
                run.log_metrics({"loss": loss}, step=step)
            for r in range(rounds):
                with run.nested(f"round_{r}", round=r):
                    run.log_metrics({"val_iou": v}, step=r)     # goes to the child run
            run.log_artifact(metrics_json)
            run.log_model(checkpoint, registered_name=f"plad-{domain}")

    The run id is kept in ``run_dir/mlflow_run.json``. Entering again with the
    same ``run_dir`` resumes that run if it is not FINISHED (a killed training
    re-run continues its run) and was started with the same params, store and
    experiment; otherwise a new run starts. Params are logged only for a new run.
    Exiting ends the run FINISHED, or FAILED (KILLED for KeyboardInterrupt) when
    an exception escapes; exceptions always propagate.

    The run goes to its domain's experiment, ``plad-<domain>``
    (:func:`plad.tracking.store.domain_experiment`), a pipeline run (``row="pipeline"``: the report, whose
    ``domain`` lists several) to ``plad``, unless ``experiment`` names another.

    The run is nested under its row run (:mod:`plad.tracking.rows`): ``row="result"``
    (the default) the row of ``(profile, domain, method)`` (method ``sp`` when none
    is given), ``row="pipeline"`` the profile's pipeline run, ``row=None`` none (a
    top-level run). Inside another active MLflow run (e.g. a flow's own) the run
    nests under that one instead. :meth:`log_result` writes the row's numbers.
    """

    def __init__(self, stage: str, domain: str, params: Mapping[str, Any] | Any,
                 run_dir: str | os.PathLike, *, method: str | None = None,
                 tags: Mapping[str, Any] | None = None, experiment: str | None = None,
                 params_path: str | os.PathLike = "params.yaml", row: str | None = RESULT):
        if row not in (RESULT, PIPELINE, None):
            raise ValueError(f"StageRun row {row!r}: expected {RESULT!r}, {PIPELINE!r} or None")
        # chosen here, so that a bad domain is an error before anything is written
        self.domain_experiments = experiment is None   # rows of another domain go to that domain's experiment
        if experiment is None:
            experiment = PIPELINE_EXPERIMENT if row == PIPELINE else domain_experiment(domain)
        self.stage = stage
        self.domain = domain
        self.method = method
        self.row_kind = row
        self.row: Row | None = None
        self.row_id: str | None = None
        self._uri: str | None = None
        self.params = flatten_params(params if params is not None else {})
        # the resolved params' hash, the number the stage's metrics files stamp (plad.provenance): a run
        # folder's MLflow run is resumed only if it was started with the same one
        self.params_hash = params_hash(params if params is not None else {})
        self.run_dir = Path(run_dir)
        self.extra_tags = dict(tags or {})
        self.experiment = experiment
        self.params_path = params_path
        self.resumed = False
        self._run_id: str | None = None
        self._exp_id: str | None = None
        self._tags: dict[str, str] | None = None
        self._stack: list[str] = []          # open runs, innermost last

    # -- state -------------------------------------------------------------------------
    @property
    def run_id(self) -> str:
        if self._run_id is None:
            raise RuntimeError("StageRun.run_id is only known once the run has started")
        return self._run_id

    @property
    def experiment_id(self) -> str:
        if self._exp_id is None:
            raise RuntimeError("StageRun.experiment_id is only known once the run has started")
        return self._exp_id

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

    def _resumable(self, mlflow_client: Any, uri: str, experiment_id: str) -> str | None:
        try:
            record = json.loads(self.run_file.read_text())
            run_id = record["run_id"]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if (record.get("tracking_uri"), record.get("experiment_id"), record.get("params_hash")) != \
                (uri, experiment_id, self.params_hash):
            return None
        try:
            run = mlflow_client.get_run(run_id)
        except Exception:  # unknown run (store reset): start afresh
            return None
        info = run.info
        if info.status == "FINISHED" or info.lifecycle_stage != "active" \
                or info.experiment_id != experiment_id:
            return None
        return run_id

    # -- context manager --------------------------------------------------------------------
    def __enter__(self) -> StageRun:
        # a store that cannot be opened or written is one line (plad.tracking.store.StoreError), before
        # anything is written; so is a store that fails while the run starts (e.g. locked or full)
        uri = open_store(write=True)
        with store_errors(uri, "cannot start the run"):
            return self._start(uri)

    def _start(self, uri: str) -> StageRun:
        self._uri = uri
        mlflow = mlflow_module()
        mlflow_client = mlflow.MlflowClient()
        experiment_id = self._exp_id = ensure_experiment(mlflow_client, uri, self.experiment)
        mark_training_experiment(mlflow_client, experiment_id,
                                 domain=None if self.row_kind == PIPELINE else self.domain)
        tags = self._tags = self.tags
        previous = self._resumable(mlflow_client, uri, experiment_id)
        nested = mlflow.active_run() is not None   # e.g. a flow's own run around the stage
        if not nested and self.row_kind is not None:
            profile = tags["plad.profile"]
            self.row = Row(profile) if self.row_kind == PIPELINE else Row(profile, self.domain, self.method or SP)
            self.row_id = row_run(mlflow_client, uri, experiment_id, self.row)
        if previous is not None:
            active = mlflow.start_run(run_id=previous, nested=nested)
            self.resumed = True
            if self.row_id is not None and "mlflow.parentRunId" not in active.data.tags:
                tags = {**tags, "mlflow.parentRunId": self.row_id}   # a run from before rows: under its row
            mlflow_client.log_batch(previous, tags=_tag_entities(tags))
        else:
            # under its row the stage's name is enough (the row names domain and method)
            name = self.stage if self.row_id is not None else \
                "/".join(x for x in (self.stage, self.method, self.domain) if x)
            active = mlflow.start_run(experiment_id=experiment_id, run_name=name, nested=nested,
                                      parent_run_id=self.row_id, tags=tags)
            self.resumed = False
        self._run_id = active.info.run_id
        self._stack = [self._run_id]
        try:
            if self.row_id is not None:
                set_row_status(mlflow_client, self.row_id, "RUNNING")
            if not self.resumed:
                _log_params(self._run_id, self.params)
            atomic_write_text(self.run_file, json.dumps({
                "run_id": self._run_id, "experiment_id": experiment_id, "tracking_uri": uri,
                "params_hash": self.params_hash, "stage": self.stage,
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
            self._end(mlflow_module(), status)
        except Exception:
            if exc_type is None:
                raise
            warnings.warn(f"could not end MLflow run {self._run_id} as {status}", stacklevel=2)
        return False  # never swallow the exception

    def _end(self, mlflow: Any, status: str) -> None:
        # close anything left open above our run (a leaked child), then our run
        while True:
            active = mlflow.active_run()
            if active is None:
                break
            mlflow.end_run(status)
            if active.info.run_id == self._run_id:
                break
        self._stack = []
        if self.row_id is not None:
            set_row_status(client(), self.row_id, status)

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
        _set_tags(self._current(), tags)

    def log_artifact(self, path: str | os.PathLike, artifact_path: str | None = None) -> None:
        """A file (or a whole directory) as artifact(s) of the innermost open run."""
        mlflow_client = client()
        path = Path(path)
        if path.is_dir():
            mlflow_client.log_artifacts(self._current(), str(path), artifact_path)
        else:
            mlflow_client.log_artifact(self._current(), str(path), artifact_path)

    # -- the row -----------------------------------------------------------------------------
    def log_result(self, *, domain: str | None = None, method: str | None = None, **values: Any) -> None:
        """The headline numbers of a result row (:func:`plad.tracking.rows.log_result`'s keywords: ``metric``,
        ``higher_is_better``, ``test``, ``val``, ``seconds_per_shape``, ``train_seconds``, ``stopped``).

        Without ``domain``/``method``: this run's own row. With them: that row of the same profile (created
        if needed), e.g. the floor baseline that SP's evaluation also scores, or every row from the report.
        """
        if self.row is None or self._exp_id is None:
            raise RuntimeError("StageRun.log_result: this run has no row (row=None, or inside another run)")
        mlflow_client = client()
        if domain is None and method is None:
            row, run_id, experiment_id = self.row, self.row_id, self._exp_id
        else:
            row = Row(self.row.profile, domain or self.domain, method or self.method or SP)
            experiment_id = self._experiment_of(mlflow_client, row.domain)
            run_id = row_run(mlflow_client, self._uri, experiment_id, row)
        if row.kind != RESULT:
            raise RuntimeError(f"StageRun.log_result: {row.name()} is not a result row")
        log_result(mlflow_client, run_id, row, **values)
        if values.get("metric") is not None:
            describe_domain(mlflow_client, experiment_id, str(row.domain), values["metric"],
                            values.get("higher_is_better"))

    def experiment_of(self, domain: str) -> str:
        """The id of the experiment that holds the result rows of ``domain`` (see :meth:`log_result`)."""
        self._current()
        return self._experiment_of(client(), domain)

    def _experiment_of(self, mlflow_client: Any, domain: str | None) -> str:
        """The id of the experiment that holds the rows of ``domain``: its own (``plad-<domain>``, created and
        marked when new), or this run's when the run was given an experiment of its own."""
        if not self.domain_experiments or domain is None or (self.row_kind != PIPELINE and domain == self.domain):
            return self.experiment_id
        experiment_id = ensure_experiment(mlflow_client, self._uri, domain_experiment(domain))
        mark_training_experiment(mlflow_client, experiment_id, domain=domain)
        return experiment_id

    def log_row_artifact(self, path: str | os.PathLike, artifact_path: str | None = None) -> None:
        """A file as an artifact of this run's row (e.g. the report's table on the pipeline run)."""
        if self.row_id is None:
            raise RuntimeError("StageRun.log_row_artifact: this run has no row")
        client().log_artifact(self.row_id, str(path), artifact_path)

    @contextlib.contextmanager
    def nested(self, name: str, **tags: Any) -> Iterator[ChildRun]:
        """A child run (``mlflow.parentRunId`` = the stage run); metrics logged inside go to it.

        Keyword tags without a dot get the ``plad.`` prefix: ``nested("round_3", round=3)``
        tags the child ``plad.round=3``. The child also carries the stage's
        ``plad.stage/domain/method/pipeline`` tags, so it is found by the same filters.
        """
        mlflow = mlflow_module()
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

        Returns ``models:/<name>/<version>`` when ``registered_name`` is given (the model is registered under
        it, or under ``<name>-<profile>`` when this run's params evaluate a subset of the test set:
        :func:`plad.tracking.registry.model_name`; the version is tagged with the run's profile and test set),
        else the logged model's URI.
        """
        current = self._current()
        active = mlflow_module().active_run()
        if active is None or active.info.run_id != current:
            raise RuntimeError("log_model must be called from the thread that entered the StageRun")
        checkpoint_path = Path(checkpoint_path)
        if not checkpoint_path.is_file():
            raise FileNotFoundError(f"{checkpoint_path}: no such checkpoint")
        if registered_name is None:
            return log_pyfunc(checkpoint_path, beam=beam)
        tags = self._tags or self.tags   # the stage run's own (a nested child carries only some)
        name = model_name(registered_name, tags)
        uri = log_pyfunc(checkpoint_path, registered_name=name, beam=beam)
        tag_version_with_run(name, uri.rsplit("/", 1)[-1], tags)
        return uri
