"""Comparing methods in MLflow's UI as a user does, in a real browser (headless Chromium, Debian's package).

A small store is filled by real stage runs (:mod:`tests.plad.tracking.ui_store`: two domains, rows SP, ST
and the floor), ``mlflow ui`` serves it on a free local port, and Chromium loads its landing page:

* each domain has its experiment, ``plad-<domain>``, listed on the landing page; from there, in a browser
  that never chose MLflow's GenAI / Model training switch, two clicks ("Model training", the experiment)
  open the domain's runs with MLflow's default columns, one row per method named with its test value; in a
  browser that chose it once, one click (the experiment);
* the chart view of a domain's experiment charts ``test_metric`` with one bar per method, all of one metric;
* the saved view "PLAD results": the same rows with their test and validation metric, seconds per shape and
  stop reason as columns.

Expected values come from the evaluation files (``results/eval/<method>/<domain>/metrics.json``), not from
MLflow. Screenshots (PNG) are written to the test's folder, and to ``$PLAD_UI_SCREENSHOTS`` when set
(how ``docs/mlflow-runs.png`` was made). Skipped where Chromium is not installed (fails under ``CI=true``,
where ``.ci/run`` installs it).
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

from plad.tracking.rows import display_name
from tests import procs
from tests.browser import Browser, chromium
from tests.conftest import under_ci
from tests.plad.tracking.ui_store import DOMAINS, METHODS, build

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
    """(tracking URI, project root, {domain: experiment id}): the stages run into a fresh store."""
    folder = tmp_path_factory.mktemp("ui-store")
    uri = f"sqlite:///{folder / 'mlflow.db'}"
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mp.delenv("PLAD_PIPELINE_ID", raising=False)
    try:
        build(folder / "project")
        import mlflow

        client = mlflow.MlflowClient(uri)
        experiments = {d: client.get_experiment_by_name(f"plad-{d}").experiment_id for d in DOMAINS}
    finally:
        mp.undo()
    return uri, folder / "project", experiments


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


def expected_rows(root: Path, domain: str) -> dict[str, dict]:
    """{method: {"name", "test"}} of a domain, and its metric, from the evaluation files of the store's project."""
    out = {}
    for method in ["sp", *METHODS, "floor"]:
        test = json.loads((root / "results" / "eval" / method / domain / "metrics.json").read_text())["test"]["mean"]
        out[method] = {"name": f"{display_name(method)} · {test:.4g}", "test": test}
    return out


def metric_of(root: Path, domain: str) -> str:
    return json.loads((root / "results" / "eval" / "sp" / domain / "metrics.json").read_text())["metric"]


def keep(shot: Path, name: str) -> None:
    """Copy a screenshot to ``$PLAD_UI_SCREENSHOTS`` (when set) for a person to look at."""
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    folder = os.environ.get("PLAD_UI_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(folder) / name)


def click(browser: Browser, selector: str, text: str) -> None:
    """A user's click on the element ``selector`` whose text is ``text`` (waits until there is one)."""
    found = f"Array.from(document.querySelectorAll({json.dumps(selector)})).find(e => e.innerText.trim() === " \
            f"{json.dumps(text)})"
    browser.wait_for(f"Boolean({found})", PAGE_TIMEOUT)
    browser.evaluate(f"{found}.click()")


# the runs page's name cells: each run's name, and whether it shows whole (not cut off with an ellipsis)
NAMES_JS = """JSON.stringify(Array.from(document.querySelectorAll(
  '.ag-row[row-id] [col-id="attributes.`Run Name`"] a[href*="/runs/"]')).map(a => {
    const cell = a.closest('.ag-cell');
    const room = cell.getBoundingClientRect().right - parseFloat(getComputedStyle(cell).paddingRight);
    return [a.innerText.trim(), a.scrollWidth <= a.clientWidth && a.getBoundingClientRect().right <= room]; }))"""


def test_the_server_reports_each_domain_experiment_as_model_training(store, ui):
    _, root, experiments = store
    for domain, experiment_id in experiments.items():
        query = urllib.parse.urlencode({"experiment_id": experiment_id})
        with urllib.request.urlopen(f"{ui}/ajax-api/2.0/mlflow/experiments/get?{query}", timeout=30) as r:
            tags = {t["key"]: t["value"] for t in json.load(r)["experiment"]["tags"]}
        assert tags["mlflow.experimentKind"] == "custom_model_development"
        # the description's first line says what the numbers in the run names are
        assert tags["mlflow.note.content"].startswith(f"PLAD, {domain}: runs named `<method> · <test "
                                                      f"{metric_of(root, domain)}>`")
        view = json.loads(tags["mlflow.sharedViewState.plad-results"])
        assert view["name"] == "PLAD results" and "groupBy" not in json.loads(view["state"])


@pytest.mark.parametrize("remembered", [False, True], ids=["new-browser", "model-training-remembered"])
def test_from_the_landing_page_two_clicks_show_each_domain_s_methods_with_their_test_metric(
        store, ui, browser, tmp_path, remembered):
    _, root, experiments = store
    if remembered:   # the user chose "Model training" once, earlier (MLflow keeps it in the browser's storage)
        browser.open(f"{ui}/")
        click(browser, "span", "Model training")
    for domain, experiment_id in experiments.items():
        rows = expected_rows(root, domain)
        browser.open(f"{ui}/health")    # a page of the same origin, so that "/" is loaded anew
        browser.wait_for("location.pathname === '/health' && document.readyState === 'complete'", PAGE_TIMEOUT)
        if not remembered:   # a browser that never chose MLflow's switch: GenAI until "Model training" is clicked
            browser.evaluate("localStorage.clear()")
        browser.open(f"{ui}/")
        # the landing page lists the experiments (its "Recent Experiments", linked as the experiment list does)
        clicks = [("a", f"plad-{domain}")] if remembered else [("span", "Model training"), ("a", f"plad-{domain}")]
        for selector, text in clicks:
            click(browser, selector, text)
        # the domain's runs page with MLflow's default columns: a row per method, its name with its test value
        browser.wait_for(f"location.hash.startsWith('#/experiments/{experiment_id}/runs') && " + " && ".join(
            f"document.body.innerText.includes({json.dumps(r['name'])})" for r in rows.values()), PAGE_TIMEOUT)
        if domain == "csg2d" and not remembered:
            keep(browser.screenshot(tmp_path / "runs.png"), "mlflow-runs.png")
        table = json.loads(browser.evaluate(ROWS_JS))
        assert sorted(r["cells"][NAME] for r in table) == sorted(r["name"] for r in rows.values())
        assert all(r["level"] == "ag-row-level-0" for r in table)   # the stage runs are folded under them
        names = dict(json.loads(browser.evaluate(NAMES_JS)))
        assert names == {r["name"]: True for r in rows.values()}     # each name whole, none cut off
        for method, row in rows.items():   # the number shown is the evaluation's test metric
            assert float(row["name"].split(" · ")[1]) == pytest.approx(row["test"], rel=5e-4), method
        # the description above the runs names the metric
        assert f"<test {metric_of(root, domain)}>" in browser.evaluate("document.body.innerText")


def test_each_domain_s_chart_compares_its_test_metric_across_methods(store, ui, browser, tmp_path):
    _, root, experiments = store
    from plad.tracking.rows import runs_path

    for domain, experiment_id in experiments.items():
        rows = expected_rows(root, domain)
        browser.open(f"{ui}/{runs_path(experiment_id)}&compareRunsMode=CHART")
        # the test_metric chart's bars: one per method, the values of this domain's evaluations (one metric)
        bars = json.loads(browser.wait_for("""(() => {
            const title = Array.from(document.querySelectorAll('h4')).find(e => e.textContent.trim() === 'test_metric');
            const plot = title && title.closest('.react-resizable').querySelector('.js-plotly-plot');
            return plot && plot.data && plot.data.length ? JSON.stringify(plot.data.flatMap(t => t.x)) : null; })()""",
                                           PAGE_TIMEOUT))
        if domain == "csg2d":
            keep(browser.screenshot(tmp_path / "chart.png"), "mlflow-chart.png")
        assert sorted(bars) == pytest.approx(sorted(r["test"] for r in rows.values()), abs=1e-6)


def test_the_results_view_shows_the_numbers_as_columns(store, ui, browser, tmp_path):
    _, root, experiments = store
    from plad.tracking.rows import results_view_path

    for domain, experiment_id in experiments.items():
        rows = expected_rows(root, domain)
        browser.open(f"{ui}/{results_view_path(experiment_id)}")
        browser.wait_for("document.querySelectorAll('[col-id=\"metrics.`test_metric`\"]').length > "
                         f"{len(rows)} && " + " && ".join(f"document.body.innerText.includes({json.dumps(r['name'])})"
                                                         for r in rows.values()), PAGE_TIMEOUT)
        table = json.loads(browser.evaluate(ROWS_JS))
        # the result rows only, sorted by name, no group (whose row would average methods and baselines)
        assert [r["cells"][NAME] for r in table] == sorted(r["name"] for r in rows.values())
        shown = {r["cells"][NAME]: r["cells"] for r in table}
        for method, row in rows.items():
            cells = shown[row["name"]]
            assert float(cells["metrics.`test_metric`"]) == pytest.approx(row["test"], abs=1e-6)
            if method != "floor":   # the floor is a baseline without a model: no validation value or timing
                assert float(cells["metrics.`val_metric`"]) > 0 and float(cells["metrics.`seconds_per_shape`"]) > 0
            if method == "st":
                assert cells["tags.`plad.stopped`"] == "max_rounds"
