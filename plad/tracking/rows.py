"""The top level of each domain's MLflow experiment: one run per row of the results table, stage runs nested under it.

Every domain has its experiment, ``plad-<domain>`` (:func:`plad.tracking.store.domain_experiment`), so that a
column or a chart of one experiment compares one metric (Chamfer distance in 2D, IoU in 3D) and a group of runs
never averages two. MLflow's experiment page lists the top-level runs of an experiment, each with its nested
runs folded under it. So that this list reads as the domain's column of the results table, every stage run
(:class:`plad.tracking.StageRun`) is started under a *row run*, one per ``(profile, domain, method)``
(``method``: a result key, e.g. ``sp``, ``lest_st``, ``search``, ``floor``, ``lest_st_ws_search_beam5``; the
rows of ``results/table.md``):

* named ``<method> · <test value>`` once its test metric is known (the experiment is the domain, its
  description names the metric): MLflow's runs page shows no metric column until one is picked there, and
  MLflow 3.17 has no per-experiment default columns, so the name is what the default page shows; its name
  column is 190 px wide, about 19 characters, hence no domain or metric name in it;
* carrying its headline numbers under the same names in every domain (:data:`TEST`, :data:`VAL`,
  :data:`SECONDS_PER_SHAPE`, :data:`TRAIN_SECONDS`; the stop reason as the tag :data:`STOPPED`), so that
  sorting and the chart view compare methods directly; the tags ``plad.metric`` and ``plad.better`` say what
  the test metric is and which way is better;
* the status of its latest stage run.

The rows of one profile are shared by every pipeline run of that profile (a re-run stage updates its row;
its earlier stage runs stay nested under it), as DVC's outputs are: the top level holds the latest
results, one row per method, not one per commit. The *pipeline run* of a profile, in the experiment
``plad`` (:data:`plad.tracking.store.PIPELINE_EXPERIMENT`), holds the report: the report stage runs under
it and logs ``table.md``, ``convergence.png`` and ``amortization.png`` to it.

Every experiment is tagged as model training (:data:`EXPERIMENT_KIND_TAG`) and described (the metric, once a
result names it: :func:`describe_domain`); a domain's is given a saved view, "PLAD results"
(:func:`results_view_state`: the row numbers as columns, every row in the charts), listed in the runs page's
Views menu and opened directly by :func:`results_view_path`.

Row runs are looked up by their tags and created on first use; on a SQLite store a file lock beside the
database keeps two stage processes from creating the same row twice.
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plad.tracking.store import sqlite_path

#: the tag telling row runs from stage runs: :data:`RESULT` or :data:`PIPELINE`
ROW_TAG = "plad.row"
RESULT = "result"
PIPELINE = "pipeline"
#: the metric names of a result row, the same in every domain
TEST = "test_metric"
VAL = "val_metric"
SECONDS_PER_SHAPE = "seconds_per_shape"
TRAIN_SECONDS = "train_seconds"
#: the stop reason of the row's training ("patience", "budget", "max_rounds", ...): a tag (metrics are numbers)
STOPPED = "plad.stopped"

#: MLflow's experiment tag that tells a model-training experiment from a GenAI one (``ExperimentKind`` in
#: MLflow's ``experiment-tracking/constants.ts``): the UI opens such an experiment on its runs, not on the
#: GenAI overview (traces, token usage). MLflow 3.17.2's UI opens an experiment by its own GenAI / Model
#: training switch instead (GenAI until switched, remembered per browser; ``?workflowType=machine_learning``
#: in the address selects it, see :func:`results_view_path`); later versions set the switch from this tag.
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
TRAINING_KIND = "custom_model_development"
#: a saved view of a domain experiment's runs (MLflow 3.17's "Views" menu; ``mlflow.sharedViewState.<key>``
#: holds ``{"name", "createdAt", "updatedAt", "state"}``, ``state`` a JSON string of the runs page's search and
#: column state) that shows the domain's results table with every number as a column
VIEW_KEY = "plad-results"
VIEW_TAG = f"mlflow.sharedViewState.{VIEW_KEY}"
VIEW_NAME = "PLAD results"
#: the experiment's description, shown above its runs (MLflow's ``mlflow.note.content``)
NOTE_TAG = "mlflow.note.content"
PIPELINE_NOTE = (
    "PLAD's pipeline runs: one `pipeline · <profile>` run per profile, with the report stage under it and its "
    "outputs (table.md, convergence.png, amortization.png, amortization.md, report.json), and the models it "
    "registers. The results of each domain, one run per method, are in the experiment `plad-<domain>`.")


def domain_note(domain: str, metric: str | None = None, higher_is_better: bool | None = None) -> str:
    """A domain experiment's description; its first line (all the runs page shows before it is expanded)
    says what the numbers in the run names are."""
    if metric is None:
        head = f"PLAD, {domain}: runs named `<method> · <test metric>`."
    else:
        better = "" if higher_is_better is None else f", {'higher' if higher_is_better else 'lower'} is better"
        head = f"PLAD, {domain}: runs named `<method> · <test {metric}>`{better}."
    return (f"{head} One run per method (a row of results/table.md) with `{TEST}`, `{VAL}`, `{SECONDS_PER_SHAPE}`,"
            f" `{TRAIN_SECONDS}` and the stop reason (tag `{STOPPED}`): Columns, or Views > \"{VIEW_NAME}\"; the "
            "chart view compares them. Expand a run for its stage runs (pretrain, finetune and its rounds, "
            "evaluate). Short names: seeded = lest_st_ws_search, +ref = with test-time refinement, b<k> = at "
            "beam k; the tag `plad.method` holds the key. The report is in the experiment `plad`.")


@dataclass(frozen=True)
class Row:
    """A row run's identity: ``(profile, domain, method)``, or the profile's pipeline run (domain ``None``)."""

    profile: str
    domain: str | None = None
    method: str | None = None

    @property
    def kind(self) -> str:
        return PIPELINE if self.domain is None else RESULT

    def name(self, test: float | None = None) -> str:
        if self.domain is None:
            return f"pipeline · {self.profile}"
        # the domain is the experiment, the metric its description: the name shows what differs
        short = display_name(str(self.method))
        return short if test is None else f"{short} · {test:.4g}"

    @property
    def tags(self) -> dict[str, str]:
        tags = {ROW_TAG: self.kind, "plad.profile": self.profile}
        if self.domain is not None:
            tags.update({"plad.domain": self.domain, "plad.method": str(self.method)})
        return tags

    def filter_string(self) -> str:
        def quoted(v: str) -> str:
            return "'" + v.replace("'", "\\'") + "'"

        return " and ".join(f"tags.`{k}` = {quoted(v)}" for k, v in self.tags.items())


def pipeline_row(profile: str) -> Row:
    return Row(profile)


def result_row(profile: str, domain: str, method: str) -> Row:
    return Row(profile, domain, method)


#: the long method keys' names on MLflow's runs page, whose name column shows about 21 characters
#: (docs/mlflow.md): the search-seeded method is "seeded", test-time refinement "+ref", a beam " b<k>"
SHORT_NAMES = {"lest_st_ws_search": "seeded", "lest_st_per_round": "per-round"}


def display_name(method: str) -> str:
    """A result key as a run name shows it: ``lest_st_ws_search_refined`` -> ``seeded+ref``,
    ``lest_st_ws_search_beam10`` -> ``seeded b10``; keys up to ``lest_st_ws`` stay as they are."""
    if method.endswith("_refined"):
        return display_name(method[: -len("_refined")]) + "+ref"
    head, _, beam = method.rpartition("_beam")
    if head and beam.isdigit():
        return f"{display_name(head)} b{beam}"
    return SHORT_NAMES.get(method, method)


# -- the experiment ------------------------------------------------------------------------------------
def _quoted(column_type: str, key: str) -> str:
    """A column of MLflow's runs table as its UI state names it, e.g. ``metrics.`test_metric```."""
    return f"{column_type}.`{key}`"


def results_view_state() -> dict[str, Any]:
    """The runs page state of the results view: result rows only, sorted by name, the row numbers as columns
    (MLflow hides metric columns until chosen), the name column wide enough for the longest method key; no
    grouping (a group's row would average methods and baselines)."""
    name = _quoted("attributes", "Run Name")
    columns = [*(_quoted("metrics", m) for m in (TEST, VAL, SECONDS_PER_SHAPE, TRAIN_SECONDS)),
               _quoted("tags", STOPPED)]
    return {"searchFilter": f"tags.`{ROW_TAG}` = '{RESULT}'", "orderByKey": "tags.`mlflow.runName`",
            "orderByAsc": True, "startTime": "ALL", "lifecycleFilter": "Active", "datasetsFilter": [],
            "modelVersionFilter": "All Runs", "selectedColumns": columns,
            # widths apply to the columns named in the order
            "columnOrder": [name, *columns], "columnWidths": {name: 300},
            # the chart view: one bar per row, every row (MLflow's default: the first 10)
            "useGroupedValuesInCharts": False, "runsHiddenMode": "SHOW_ALL"}


def runs_path(experiment_id: str) -> str:
    """The MLflow UI's address (after its root) of an experiment's runs page; ``workflowType`` because MLflow
    3.17 opens an experiment by its GenAI / model-training switch (default GenAI), not by the experiment's kind."""
    return f"#/experiments/{experiment_id}/runs?workflowType=machine_learning"


def results_view_path(experiment_id: str) -> str:
    """The MLflow UI's address (after its root) of a domain experiment's results view."""
    return f"{runs_path(experiment_id)}&viewStateShareKey={VIEW_KEY}"


def mark_training_experiment(mlflow_client: Any, experiment_id: str, *, domain: str | None = None) -> None:
    """Tag the experiment as model training (opens on its runs where MLflow follows the kind), describe it and,
    for a domain's (``domain``), save the results view, each unless already there (a kind, description or view
    changed in the UI stays)."""
    import json

    tags = mlflow_client.get_experiment(experiment_id).tags or {}
    if EXPERIMENT_KIND_TAG not in tags:
        mlflow_client.set_experiment_tag(experiment_id, EXPERIMENT_KIND_TAG, TRAINING_KIND)
    if NOTE_TAG not in tags:
        note = PIPELINE_NOTE if domain is None else domain_note(domain)
        mlflow_client.set_experiment_tag(experiment_id, NOTE_TAG, note)
    if domain is not None and VIEW_TAG not in tags:
        now = int(time.time() * 1000)
        view = {"name": VIEW_NAME, "createdAt": now, "updatedAt": now, "state": json.dumps(results_view_state())}
        mlflow_client.set_experiment_tag(experiment_id, VIEW_TAG, json.dumps(view))


def describe_domain(mlflow_client: Any, experiment_id: str, domain: str, metric: str,
                    higher_is_better: bool | None) -> None:
    """Name the test metric in a domain experiment's description once a result says which it is (the stages
    know it, :mod:`plad.tracking` does not); a description written or changed by someone else stays."""
    tags = mlflow_client.get_experiment(experiment_id).tags or {}
    note = domain_note(domain, metric, higher_is_better)
    if tags.get(NOTE_TAG) in (None, domain_note(domain)):
        mlflow_client.set_experiment_tag(experiment_id, NOTE_TAG, note)


# -- finding or creating a row run ---------------------------------------------------------------------
@contextlib.contextmanager
def _creation_lock(uri: str) -> Iterator[None]:
    """Serialize "look up, else create" of row runs between processes sharing a SQLite store."""
    db = sqlite_path(uri)
    try:
        import fcntl
    except ImportError:   # not POSIX: no lock (a race then makes a duplicate row, nothing is lost)
        fcntl = None
    if db is None or fcntl is None or not db.parent.is_dir():
        yield
        return
    # the store's own lock file (plad.tracking.store), taken here after the store is open: one lock file
    # beside a store, which .gitignore and the store's checks already know
    lock = Path(f"{db}.lock")
    with open(lock, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def find_row(mlflow_client: Any, experiment_id: str, row: Row) -> str | None:
    """The id of the (active) row run, the first created if there are several; ``None`` when there is none."""
    found = mlflow_client.search_runs([experiment_id], row.filter_string(),
                                      order_by=["attributes.start_time ASC"], max_results=1)
    return found[0].info.run_id if found else None


def row_run(mlflow_client: Any, uri: str, experiment_id: str, row: Row) -> str:
    """The id of the row run, created (FINISHED, no metrics yet) when there is none."""
    run_id = find_row(mlflow_client, experiment_id, row)
    if run_id is not None:
        return run_id
    with _creation_lock(uri):
        run_id = find_row(mlflow_client, experiment_id, row)
        if run_id is None:
            run = mlflow_client.create_run(experiment_id, run_name=row.name(), tags=row.tags)
            run_id = run.info.run_id
            mlflow_client.set_terminated(run_id, "FINISHED")
    return run_id


# -- what a row says -----------------------------------------------------------------------------------
def log_result(mlflow_client: Any, run_id: str, row: Row, *, metric: str | None = None,
               higher_is_better: bool | None = None, test: float | None = None, val: float | None = None,
               seconds_per_shape: float | None = None, train_seconds: float | None = None,
               stopped: str | None = None) -> None:
    """Log a result row's numbers (those given; ``None`` leaves a number as it was) and name it by its test
    metric."""
    from mlflow.entities import Metric, RunTag

    now = int(time.time() * 1000)
    # rounded as a table shows them (the stage runs keep the full values)
    values = {TEST: _round(test, 6), VAL: _round(val, 6), SECONDS_PER_SHAPE: _significant(seconds_per_shape, 4),
              TRAIN_SECONDS: _round(train_seconds, 1)}
    metrics = [Metric(k, v, now, 0) for k, v in values.items() if v is not None]
    tags: dict[str, str] = {}
    if metric is not None:
        tags["plad.metric"] = metric
    if higher_is_better is not None:
        tags["plad.better"] = "higher" if higher_is_better else "lower"
    if stopped is not None:
        tags[STOPPED] = str(stopped)
    if metrics or tags:
        mlflow_client.log_batch(run_id, metrics=metrics, tags=[RunTag(k, v) for k, v in tags.items()])
    if test is not None:
        mlflow_client.update_run(run_id, name=row.name(float(test)))


def _round(v: float | None, digits: int) -> float | None:
    return None if v is None else round(float(v), digits)


def _significant(v: float | None, digits: int) -> float | None:
    return None if v is None else float(f"{float(v):.{digits}g}")


def set_row_status(mlflow_client: Any, run_id: str, status: str) -> None:
    """The row shows its latest stage run's status: RUNNING while one runs, then how it ended."""
    if status == "RUNNING":
        mlflow_client.update_run(run_id, status="RUNNING")
    else:
        mlflow_client.set_terminated(run_id, status)


__all__ = ["EXPERIMENT_KIND_TAG", "NOTE_TAG", "PIPELINE", "PIPELINE_NOTE", "RESULT", "ROW_TAG", "SECONDS_PER_SHAPE",
           "STOPPED", "TEST", "TRAINING_KIND", "TRAIN_SECONDS", "VAL", "VIEW_KEY", "VIEW_NAME", "VIEW_TAG", "Row",
           "describe_domain", "display_name", "domain_note", "find_row", "log_result", "mark_training_experiment",
           "pipeline_row", "result_row", "results_view_path", "results_view_state", "row_run", "runs_path",
           "set_row_status"]
