"""plad.tracking.rows: each domain's experiment (plad-<domain>) has one top-level run per method, the stage runs
nested under it; the pipeline runs are in the experiment plad.

One SQLite store for the module; each test uses its own profile (rows are per profile), so tests do not
see each other's rows.
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import time

import pytest

from plad.tracking import StageRun
from plad.tracking import rows as R
from tests.conftest import REPO_ROOT


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("mlflow")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mp.delenv("PLAD_PIPELINE_ID", raising=False)
    import mlflow

    mlflow.set_tracking_uri(uri)
    mlflow.MlflowClient().search_experiments()   # the schema, once
    yield uri
    while mlflow.active_run() is not None:
        mlflow.end_run()
    mp.undo()


@pytest.fixture
def client(store):
    import mlflow

    return mlflow.MlflowClient(store)


def params(tmp_path, profile: str):
    path = tmp_path / "params.yaml"
    path.write_text(f"profile: {profile}\n")
    return path


def top_level(client, profile: str, experiment: str = "plad-csg2d") -> dict[str, object]:
    """{run name: run} of the top-level runs of a profile in one experiment."""
    exp = client.get_experiment_by_name(experiment).experiment_id
    found = client.search_runs([exp], f"tags.`plad.profile` = '{profile}'")
    return {r.info.run_name: r for r in found if "mlflow.parentRunId" not in r.data.tags}


def test_stage_runs_nest_under_their_row_named_by_its_test_metric(store, client, tmp_path):
    p = params(tmp_path, "rows-a")
    with StageRun("finetune", "csg2d", {}, tmp_path / "ft", method="st", params_path=p) as ft:
        assert client.get_run(ft.row_id).info.status == "RUNNING"   # the row shows its running stage
        ft.log_result(metric="chamfer", higher_is_better=False, val=1.23456789, train_seconds=12.345,
                      stopped="patience")
    with StageRun("evaluate", "csg2d", {}, tmp_path / "ev", method="st", params_path=p) as ev:
        ev.log_result(metric="chamfer", higher_is_better=False, test=1.5, seconds_per_shape=0.012345678)
        ev.log_result(method="floor", metric="chamfer", higher_is_better=False, test=3.0)
    assert ft.row_id == ev.row_id
    row = client.get_run(ev.row_id)
    # the domain is the experiment, the metric its description: the name is the method and its test value
    assert row.info.run_name == "st · 1.5" and row.info.status == "FINISHED"
    exp = client.get_experiment_by_name("plad-csg2d")
    assert row.info.experiment_id == exp.experiment_id
    assert exp.tags[R.NOTE_TAG].startswith("PLAD, csg2d: runs named `<method> · <test chamfer>`, lower is better.")
    # the same names in every domain, rounded as a table shows them
    assert row.data.metrics == {"test_metric": 1.5, "val_metric": 1.234568, "seconds_per_shape": 0.01235,
                                "train_seconds": 12.3}
    tags = row.data.tags
    assert {k: tags[k] for k in ("plad.row", "plad.profile", "plad.domain", "plad.method", "plad.metric",
                                 "plad.better", "plad.stopped")} == {
        "plad.row": "result", "plad.profile": "rows-a", "plad.domain": "csg2d", "plad.method": "st",
        "plad.metric": "chamfer", "plad.better": "lower", "plad.stopped": "patience"}
    # a row is no stage run: filters on a stage or a pipeline find the stage runs only
    assert "plad.stage" not in tags and "plad.pipeline" not in tags and "mlflow.parentRunId" not in tags
    for stage, run in (("finetune", ft), ("evaluate", ev)):
        got = client.get_run(run.run_id)
        assert got.data.tags["mlflow.parentRunId"] == row.info.run_id and got.info.run_name == stage
        assert got.data.tags["plad.stage"] == stage and got.data.tags["plad.method"] == "st"
    # nested runs of a stage (rounds) stay under the stage run
    top = top_level(client, "rows-a")
    assert sorted(top) == ["floor · 3", "st · 1.5"]
    floor = top["floor · 3"]
    assert floor.data.metrics == {"test_metric": 3.0} and floor.data.tags["plad.method"] == "floor"


def test_a_row_shows_how_its_latest_stage_run_ended(store, client, tmp_path):
    p = params(tmp_path, "rows-b")
    with pytest.raises(RuntimeError, match="boom"):
        with StageRun("evaluate", "csg3d", {"beam": 1}, tmp_path / "ev", method="ws", params_path=p) as first:
            raise RuntimeError("boom")
    assert client.get_run(first.row_id).info.status == "FAILED"
    with StageRun("evaluate", "csg3d", {"beam": 1}, tmp_path / "ev", method="ws", params_path=p) as again:
        again.log_result(metric="iou", higher_is_better=True, test=0.61234)
    assert again.resumed and again.row_id == first.row_id
    row = client.get_run(first.row_id)
    assert row.info.status == "FINISHED" and row.info.run_name == "ws · 0.6123"
    assert row.info.experiment_id == client.get_experiment_by_name("plad-csg3d").experiment_id
    assert row.data.tags["plad.better"] == "higher"


def test_a_row_per_profile_and_the_pipeline_row_holds_the_report(store, client, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    with StageRun("pretrain", "csg2d", {}, a / "pre", params_path=params(a, "rows-c")) as pre_c:
        pre_c.log_result(train_seconds=60.04, stopped="budget")   # no method: SP's row
    with StageRun("pretrain", "csg2d", {}, b / "pre", params_path=params(b, "rows-d")) as pre_d:
        pass
    assert pre_c.row_id != pre_d.row_id
    assert client.get_run(pre_c.row_id).info.run_name == "sp"   # no test metric yet
    table = tmp_path / "table.md"
    table.write_text("| method | 2D CSG |\n")
    with StageRun("report", "csg2d,csg3d", {}, a / "rep", params_path=a / "params.yaml", row=R.PIPELINE) as rep:
        rep.log_row_artifact(table)
        rep.log_result(domain="csg2d", method="sp", metric="chamfer", higher_is_better=False, test=2.5, val=2.4)
        # a domain no stage has run yet: its experiment is made, described and given its view
        rep.log_result(domain="csg3d", method="floor", metric="iou", higher_is_better=True, test=0.25)
        with pytest.raises(RuntimeError, match="not a result row"):
            rep.log_result(test=1.0)
    # the pipeline run is in the experiment plad; each domain's rows in the domain's
    assert client.get_run(rep.row_id).info.experiment_id == client.get_experiment_by_name("plad").experiment_id
    csg3d = client.get_experiment_by_name("plad-csg3d")
    assert R.VIEW_TAG in csg3d.tags and "test iou>`, higher is better" in csg3d.tags[R.NOTE_TAG]
    assert list(top_level(client, "rows-c", "plad-csg3d")) == ["floor · 0.25"]
    pipeline = client.get_run(rep.row_id)
    assert pipeline.info.run_name == "pipeline · rows-c" and pipeline.data.tags["plad.row"] == "pipeline"
    assert [f.path for f in client.list_artifacts(rep.row_id)] == ["table.md"]
    assert client.get_run(rep.run_id).data.tags["mlflow.parentRunId"] == rep.row_id
    sp = client.get_run(pre_c.row_id)
    assert sp.info.run_name == "sp · 2.5"
    assert sp.data.metrics == {"train_seconds": 60.0, "test_metric": 2.5, "val_metric": 2.4}
    assert sorted(top_level(client, "rows-c")) == ["sp · 2.5"]
    assert sorted(top_level(client, "rows-c", "plad")) == ["pipeline · rows-c"]


def test_without_a_row_or_inside_another_run_a_stage_run_is_not_under_a_row(store, client, tmp_path):
    import mlflow

    p = params(tmp_path, "rows-e")
    with StageRun("evaluate", "csg2d", {}, tmp_path / "a", method="st", params_path=p, row=None) as alone:
        with pytest.raises(RuntimeError, match="no row"):
            alone.log_result(test=1.0)
    assert alone.row_id is None and "mlflow.parentRunId" not in client.get_run(alone.run_id).data.tags
    exp = client.get_experiment_by_name("plad-csg2d").experiment_id
    with mlflow.start_run(experiment_id=exp, run_name="a flow") as flow:
        with StageRun("evaluate", "csg2d", {}, tmp_path / "b", method="st", params_path=p) as inner:
            pass
    assert inner.row_id is None and client.get_run(inner.run_id).data.tags["mlflow.parentRunId"] == \
        flow.info.run_id
    assert list(top_level(client, "rows-e")) == ["evaluate/st/csg2d"]   # the run without a row, as before
    with pytest.raises(ValueError, match="row"):
        StageRun("evaluate", "csg2d", {}, tmp_path / "c", row="results")
    # a list of domains is no domain: its experiment would be neither
    with pytest.raises(ValueError, match=r"MLflow experiment of domain 'csg2d,csg3d': expected one domain name"):
        StageRun("evaluate", "csg2d,csg3d", {}, tmp_path / "d")


def test_the_experiment_is_marked_as_model_training_once(store, client, tmp_path):
    with StageRun("evaluate", "csg2d", {}, tmp_path / "a", method="st", params_path=params(tmp_path, "rows-f")):
        pass
    exp = client.get_experiment_by_name("plad-csg2d")
    tags = exp.tags
    assert tags[R.EXPERIMENT_KIND_TAG] == "custom_model_development" and "PLAD, csg2d" in tags[R.NOTE_TAG]
    view = json.loads(tags[R.VIEW_TAG])
    assert view["name"] == R.VIEW_NAME and json.loads(view["state"]) == R.results_view_state()
    # no grouping: a group's row would average methods and baselines
    assert "groupBy" not in json.loads(view["state"])
    assert R.results_view_path(exp.experiment_id) == (
        f"#/experiments/{exp.experiment_id}/runs?workflowType=machine_learning&viewStateShareKey=plad-results")
    # a user's choice in the UI stays
    client.set_experiment_tag(exp.experiment_id, R.EXPERIMENT_KIND_TAG, "genai_development")
    with StageRun("evaluate", "csg2d", {}, tmp_path / "b", method="st", params_path=params(tmp_path, "rows-f")):
        pass
    assert client.get_experiment(exp.experiment_id).tags[R.EXPERIMENT_KIND_TAG] == "genai_development"
    client.set_experiment_tag(exp.experiment_id, R.EXPERIMENT_KIND_TAG, "custom_model_development")


def test_a_row_being_created_elsewhere_is_found_not_duplicated(store, client, tmp_path):
    """A second stage process asks for a row while the first holds the creation lock: once the lock is
    released it finds the first one's row instead of creating another."""
    from plad.tracking.store import ensure_experiment

    exp = ensure_experiment(client, store, "plad-csg2d")
    row = R.Row("rows-race", "csg2d", "st")
    ready = tmp_path / "ready"
    script = textwrap.dedent(f"""
        import pathlib, mlflow
        from plad.tracking import rows as R
        client = mlflow.MlflowClient()
        pathlib.Path({str(ready)!r}).write_text("")
        print(R.row_run(client, {store!r}, {exp!r}, R.Row("rows-race", "csg2d", "st")))
    """)
    with R._creation_lock(store):
        other = subprocess.Popen([sys.executable, "-c", script], cwd=REPO_ROOT, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        while not ready.exists() and other.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)   # its first look-up (milliseconds) finds nothing; then it waits for the lock
        assert other.poll() is None, other.stderr.read()
        mine = client.create_run(exp, run_name=row.name(), tags=row.tags).info.run_id
    out, err = other.communicate(timeout=120)
    assert other.returncode == 0, err
    assert out.split()[-1] == mine
    assert R.find_row(client, exp, row) == mine
    assert len(client.search_runs([exp], row.filter_string())) == 1


def test_long_method_keys_get_names_the_runs_page_shows_whole():
    assert [R.display_name(k) for k in ("st", "lest_st_ws", "lest_st_ws_search", "lest_st_ws_search_refined",
                                         "lest_st_ws_search_beam10", "lest_st_per_round", "taught_refined")] == [
        "st", "lest_st_ws", "seeded", "seeded+ref", "seeded b10", "per-round", "taught+ref"]
    # every key the results table has fits the name column with a metric of 4 significant digits
    keys = ["sp", "rl", "ws", "st", "lest", "lest_st", "lest_st_ws", "lest_st_per_round", "lest_st_ws_search",
            "lest_st_ws_search_refined", "lest_st_ws_search_beam1", "lest_st_ws_search_beam5",
            "lest_st_ws_search_beam10", "search", "floor", "taught", "taught_refined"]
    assert max(len(R.Row("p", "csg2d", k).name(0.8613)) for k in keys) <= 19
