"""Comparing methods in MLflow's UI as a user does, in a real browser (headless Chromium, Debian's package).

A small store is filled by real stage runs (:mod:`tests.plad.tracking.ui_store`: two domains, rows SP, ST
and the floor), ``mlflow ui`` serves it on a free local port, and Chromium loads the experiment page:

* with nothing chosen (MLflow's default columns): the experiment opens on its runs, whose top level is
  one row per (domain, method) plus the pipeline's, each named with its test metric;
* the saved view "PLAD results by domain": the same rows grouped by domain with their test and
  validation metric, seconds per shape and stop reason as columns, and one bar per row in the chart view.

Expected values come from the evaluation files (``results/eval/<method>/<domain>/metrics.json``), not from
MLflow. Screenshots (PNG) are written to the test's folder, and to ``$PLAD_UI_SCREENSHOTS`` when set
(how ``docs/mlflow-results-view.png`` was made). Skipped where Chromium is not installed (fails under
``CI=true``, where ``.ci/run`` installs it).
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from tests import procs
from tests.browser import Browser, chromium
from tests.conftest import under_ci
from tests.plad.tracking.ui_store import DOMAINS, METHODS, PROFILE, build

pytestmark = pytest.mark.integration

#: MLflow's UI on a busy 2-core machine: a server start, a first page load
SERVER_TIMEOUT = 180
PAGE_TIMEOUT = 180

# every row of the runs table, in display order: its id, nesting level and cell texts by column
ROWS_JS = """JSON.stringify(Array.from(document.querySelectorAll('.ag-row[row-id]')).reduce((rows, r) => {
  const id = r.getAttribute('row-id');
  let row = rows.find(x => x.id === id);
  if (!row) { row = {id, index: Number(r.getAttribute('row-index')), cells: {}, run: false,
                     level: [...r.classList].find(c => c.startsWith('ag-row-level-'))}; rows.push(row); }
  row.run = row.run || Boolean(r.querySelector('a[href*="/runs/"]'));   // a run's row, not a group's
  for (const c of r.querySelectorAll('[col-id]')) {
    // a run's name is its link (the cell also holds its color's label); a group's, the cell's first line
    const link = c.querySelector('a[href*="/runs/"]');
    row.cells[c.getAttribute('col-id')] = (link ? link.innerText : c.innerText.split('\\n')[0]).trim();
  }
  return rows;
}, []).sort((a, b) => a.index - b.index))"""
NAME = "attributes.`Run Name`"


@pytest.fixture(scope="module")
def browser_needed():
    if chromium() is None:
        message = "chromium is not installed (Debian: apt-get install chromium)"
        if under_ci():
            pytest.fail(f"CI=true and {message}")
        pytest.skip(message)


@pytest.fixture(scope="module")
def store(browser_needed, tmp_path_factory):
    """(tracking URI, project root, experiment id): the stages run into a fresh store."""
    folder = tmp_path_factory.mktemp("ui-store")
    uri = f"sqlite:///{folder / 'mlflow.db'}"
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mp.delenv("PLAD_PIPELINE_ID", raising=False)
    try:
        build(folder / "project")
        import mlflow

        experiment_id = mlflow.MlflowClient(uri).get_experiment_by_name("plad").experiment_id
    finally:
        mp.undo()
    return uri, folder / "project", experiment_id


@pytest.fixture(scope="module")
def ui(store, tmp_path_factory):
    """The base URL of ``mlflow ui`` serving the store (one worker, no job runner: nothing here needs one)."""
    uri, *_ = store
    log = tmp_path_factory.mktemp("ui") / "mlflow-ui.log"
    port = procs.free_port()
    mlflow_cli = str(Path(sys.executable).with_name("mlflow"))
    proc = procs.start([mlflow_cli if os.path.exists(mlflow_cli) else "mlflow", "ui", "--backend-store-uri", uri,
                        "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
                       procs.child_env(MLFLOW_SERVER_ENABLE_JOB_EXECUTION="false"), log)
    try:
        procs.wait_http(f"http://127.0.0.1:{port}/health", proc, log, SERVER_TIMEOUT)
        yield f"http://127.0.0.1:{port}"
    finally:
        procs.stop(proc)


@pytest.fixture
def browser(browser_needed, tmp_path):
    b = Browser(tmp_path)
    try:
        yield b
    finally:
        b.close()


def expected_rows(root: Path) -> dict[tuple[str, str], dict]:
    """{(domain, method): {"name", "test", "metric"}} from the evaluation files of the store's project."""
    out = {}
    for domain in DOMAINS:
        for method in ["sp", *METHODS, "floor"]:
            m = json.loads((root / "results" / "eval" / method / domain / "metrics.json").read_text())
            metric = m["metric"] if method != "floor" else json.loads(
                (root / "results" / "eval" / "sp" / domain / "metrics.json").read_text())["metric"]
            test = m["test"]["mean"]
            out[(domain, method)] = {"name": f"{domain} · {method} · {metric} {test:.4g}", "test": test,
                                     "metric": metric}
    return out


def keep(shot: Path, name: str) -> None:
    """Copy a screenshot to ``$PLAD_UI_SCREENSHOTS`` (when set) for a person to look at."""
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    folder = os.environ.get("PLAD_UI_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(folder) / name)


def test_the_server_reports_the_experiment_as_model_training(store, ui):
    _, _, experiment_id = store
    query = urllib.parse.urlencode({"experiment_id": experiment_id})
    with urllib.request.urlopen(f"{ui}/ajax-api/2.0/mlflow/experiments/get?{query}", timeout=30) as r:
        tags = {t["key"]: t["value"] for t in json.load(r)["experiment"]["tags"]}
    assert tags["mlflow.experimentKind"] == "custom_model_development"
    view = json.loads(tags["mlflow.sharedViewState.plad-results"])
    assert view["name"] == "PLAD results by domain" and json.loads(view["state"])["groupBy"]["groupByKeys"] == [
        {"mode": "tag", "groupByData": "plad.domain"}]


def test_the_runs_top_level_is_one_row_per_domain_and_method_named_with_its_test_metric(store, ui, browser,
                                                                                        tmp_path):
    _, root, experiment_id = store
    rows = expected_rows(root)
    # the experiment's address as the experiment list links it, with MLflow 3.17's model-training switch
    browser.open(f"{ui}/#/experiments/{experiment_id}?workflowType=machine_learning")
    names = [r["name"] for r in rows.values()]
    browser.wait_for("location.hash.includes('/runs') && " + " && ".join(
        f"document.body.innerText.includes({json.dumps(n)})" for n in names), PAGE_TIMEOUT)
    keep(browser.screenshot(tmp_path / "runs.png"), "mlflow-runs.png")
    table = json.loads(browser.evaluate(ROWS_JS))
    top = [r["cells"][NAME] for r in table if r["level"] == "ag-row-level-0"]
    # every row of the comparison and the pipeline's, nothing else: the stage runs are folded under them
    assert sorted(top) == sorted([*names, f"pipeline · {PROFILE}"])
    assert len(top) == len(table)


def test_the_results_view_compares_methods_per_domain(store, ui, browser, tmp_path):
    _, root, experiment_id = store
    rows = expected_rows(root)
    from plad.tracking.rows import results_view_path

    browser.open(f"{ui}/{results_view_path(experiment_id)}")
    browser.wait_for("document.querySelectorAll('[col-id=\"metrics.`test_metric`\"]').length > "
                     f"{len(rows)} && " + " && ".join(f"document.body.innerText.includes({json.dumps(r['name'])})"
                                                     for r in rows.values()), PAGE_TIMEOUT)
    keep(browser.screenshot(tmp_path / "results-view.png"), "mlflow-results-view.png")
    table = json.loads(browser.evaluate(ROWS_JS))
    # a group per domain, each followed by its rows (sorted by name): the result rows only
    assert [r["cells"][NAME] for r in table] == [x for d in sorted(DOMAINS) for x in [
        f"Group: {d}", *sorted(r["name"] for (domain, _), r in rows.items() if domain == d)]]
    members = [r["cells"] for r in table if r["run"]]
    shown = {c[NAME]: c for c in members}
    for (_, method), row in rows.items():
        cells = shown[row["name"]]
        assert float(cells["metrics.`test_metric`"]) == pytest.approx(row["test"], abs=1e-6)
        assert cells["tags.`plad.metric`"] == row["metric"]
        if method != "floor":   # the floor is a baseline without a model: no validation value or timing
            assert float(cells["metrics.`val_metric`"]) > 0 and float(cells["metrics.`seconds_per_shape`"]) > 0
        if method == "st":
            assert cells["tags.`plad.stopped`"] == "max_rounds"
    # the chart view of the same view: a test_metric chart with one bar per row (not one per domain group)
    browser.open(f"{ui}/{results_view_path(experiment_id)}&compareRunsMode=CHART")
    bars = browser.wait_for("""(() => {
        const title = Array.from(document.querySelectorAll('h4')).find(e => e.textContent.trim() === 'test_metric');
        const card = title && title.closest('.react-resizable');
        return card ? card.querySelectorAll('.barlayer .point').length : 0; })()""", PAGE_TIMEOUT)
    keep(browser.screenshot(tmp_path / "results-chart.png"), "mlflow-results-chart.png")
    assert bars == len(rows)
