"""plad.tracking: stage runs in MLflow (params, metrics, artifacts, resume, nesting, models).

One SQLite store per session (a new database runs migrations, about 3 s);
every test uses its own run directory and, where it matters, its own
pipeline id, so tests do not see each other's runs.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from plad import tracking
from plad.tracking import StageRun, pipeline_tags
from tests.conftest import REPO_ROOT


@pytest.fixture(scope="session")
def store(tmp_path_factory):
    """A session-wide SQLite store; yields (tracking uri, store directory)."""
    root = tmp_path_factory.mktemp("mlflow")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mp.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    mp.delenv("PLAD_PIPELINE_ID", raising=False)
    import mlflow

    mlflow.set_tracking_uri(uri)
    mlflow.MlflowClient().search_experiments()  # create the schema once, here
    yield uri, root
    while mlflow.active_run() is not None:
        mlflow.end_run()
    mp.undo()


@pytest.fixture
def client(store):
    import mlflow

    return mlflow.MlflowClient(store[0])


def test_import_is_cheap():
    code = "import sys, plad.tracking; assert 'mlflow' not in sys.modules and 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, check=True)


def test_tracking_uri_default_is_absolute_sqlite(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    assert tracking.tracking_uri() == f"sqlite:///{tmp_path.resolve() / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:5000")
    assert tracking.tracking_uri() == "http://127.0.0.1:5000"


def test_pipeline_tags_follow_params_bytes(tmp_path, monkeypatch):
    monkeypatch.delenv("PLAD_PIPELINE_ID", raising=False)
    a, a2, b = tmp_path / "a.yaml", tmp_path / "a2.yaml", tmp_path / "b.yaml"
    a.write_text("profile: smoke\ntrain:\n  lr: 0.001\n")
    a2.write_bytes(a.read_bytes())
    b.write_text("profile: smoke\ntrain:\n  lr: 0.002\n")
    ta = pipeline_tags(a)
    assert ta == pipeline_tags(a) == pipeline_tags(a2)
    assert ta["plad.pipeline"] != pipeline_tags(b)["plad.pipeline"]
    assert ta["plad.profile"] == "smoke" and ta["plad.git_rev"] == "nogit"  # tmp_path is no git repo
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "smoke.yaml").write_text("train: {lr: 0.01}\n")   # the profile's overrides count too
    with_profile = pipeline_tags(a)["plad.pipeline"]
    assert with_profile != ta["plad.pipeline"]
    (tmp_path / "profiles" / "smoke.yaml").write_text("train: {lr: 0.02}\n")
    assert pipeline_tags(a)["plad.pipeline"] not in (with_profile, ta["plad.pipeline"])
    b.write_text("train: {}\n")
    assert pipeline_tags(b)["plad.profile"] == "custom"
    monkeypatch.setenv("PLAD_PIPELINE_ID", "orchestrated-7")
    assert pipeline_tags(a)["plad.pipeline"] == "orchestrated-7"


def test_flatten_params():
    flat = tracking.flatten_params({"train": {"lr": 0.1, "sizes": [1, 2]}, "x": None, "long": "y" * 7000})
    assert flat == {"train.lr": "0.1", "train.sizes": "[1, 2]", "x": "None", "long": "y" * 6000}


def test_stage_run_logs_params_metrics_artifact(store, client, tmp_path, monkeypatch):
    import mlflow

    uri, root = store
    monkeypatch.setenv("PLAD_PIPELINE_ID", "test-basic")
    report = tmp_path / "report.json"
    report.write_text('{"iou": 0.5}')
    params = {"epochs": 2, "opt": {"lr": 1e-3, "betas": [0.9, 0.99]}, "blob": "z" * 7000}
    with StageRun("pretrain", "csg2d", params, tmp_path / "run", method="plad",
                  tags={"owner": "tests"}) as run:
        run.log_metrics({"loss": 2.0}, step=0)
        run.log_metrics({"loss": 1.0, "acc": 0.5}, step=1)
        run.log_artifact(report)
        run.log_artifact(report, artifact_path="reports")
    got = client.get_run(run.run_id)
    assert got.info.status == "FINISHED"
    assert got.data.params["epochs"] == "2"
    assert got.data.params["opt.betas"] == "[0.9, 0.99]"
    assert len(got.data.params["blob"]) == 6000
    assert got.data.metrics == {"loss": 1.0, "acc": 0.5}
    assert [m.value for m in client.get_metric_history(run.run_id, "loss")] == [2.0, 1.0]
    tags = got.data.tags
    assert tags["plad.stage"] == "pretrain" and tags["plad.domain"] == "csg2d"
    assert tags["plad.method"] == "plad" and tags["owner"] == "tests"
    assert tags["plad.pipeline"] == "test-basic" and "plad.git_rev" in tags and "plad.profile" in tags
    paths = {a.path for a in client.list_artifacts(run.run_id)}
    assert {"report.json", "reports"} <= paths
    # artifacts live beside the database, not under the current directory
    assert got.info.artifact_uri.startswith(root.as_uri())
    assert json.loads((tmp_path / "run" / "mlflow_run.json").read_text())["run_id"] == run.run_id
    # in its domain's experiment
    found = mlflow.search_runs(experiment_names=["plad-csg2d"],
                               filter_string="tags.`plad.pipeline` = 'test-basic'")
    assert list(found["run_id"]) == [run.run_id]


def test_exception_fails_run_and_propagates(store, client, tmp_path):
    with pytest.raises(ZeroDivisionError):
        with StageRun("train", "csg2d", {"a": 1}, tmp_path) as run:
            1 / 0  # noqa: B018 (the exception under test)
    assert client.get_run(run.run_id).info.status == "FAILED"


def test_killed_process_run_is_resumed_finished_is_not(store, client, tmp_path):
    run_dir = tmp_path / "run"
    params = {"lr": 0.1}
    # a process killed mid-stage: never reaches __exit__, the run stays RUNNING
    script = textwrap.dedent(f"""
        import os
        from plad.tracking import StageRun
        run = StageRun("finetune", "csg2d", {params!r}, {str(run_dir)!r}, method="plad").__enter__()
        run.log_metrics({{"loss": 3.0}}, step=0)
        print(run.run_id, flush=True)
        os._exit(9)
    """)
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True,
                         text=True, env=os.environ.copy())
    assert out.returncode == 9, out.stderr
    killed_id = out.stdout.split()[-1]
    assert client.get_run(killed_id).info.status == "RUNNING"

    with StageRun("finetune", "csg2d", params, run_dir, method="plad") as run:
        assert run.resumed and run.run_id == killed_id
        run.log_metrics({"loss": 2.0}, step=1)
    assert [m.value for m in client.get_metric_history(killed_id, "loss")] == [3.0, 2.0]
    assert client.get_run(killed_id).info.status == "FINISHED"

    # a finished stage re-run starts a new run
    with StageRun("finetune", "csg2d", params, run_dir, method="plad") as again:
        assert not again.resumed and again.run_id != killed_id


def test_failed_run_is_resumed_unless_params_changed(store, client, tmp_path):
    with pytest.raises(RuntimeError):
        with StageRun("train", "csg2d", {"lr": 0.1}, tmp_path) as first:
            raise RuntimeError("boom")
    assert client.get_run(first.run_id).info.status == "FAILED"
    with StageRun("train", "csg2d", {"lr": 0.1}, tmp_path) as second:
        pass
    assert second.resumed and second.run_id == first.run_id
    assert client.get_run(first.run_id).info.status == "FINISHED"
    # the run folder keeps the params hash a stage's metrics files stamp: one number for one run's params
    from plad.provenance import params_hash
    assert json.loads((tmp_path / "mlflow_run.json").read_text())["params_hash"] == params_hash({"lr": 0.1})

    with pytest.raises(RuntimeError):
        with StageRun("train", "csg2d", {"lr": 0.1}, tmp_path) as third:
            raise RuntimeError("boom")
    # other params: a new run (MLflow params cannot be overwritten)
    with StageRun("train", "csg2d", {"lr": 0.2}, tmp_path) as fourth:
        pass
    assert not fourth.resumed and fourth.run_id != third.run_id
    assert client.get_run(fourth.run_id).data.params == {"lr": "0.2"}


def test_nested_round_runs(store, client, tmp_path):
    with StageRun("finetune", "csg2d", {}, tmp_path, method="plad") as run:
        children = []
        for r in range(2):
            with run.nested(f"round_{r}", round=r) as child:
                run.log_metrics({"val_iou": 0.5 + r}, step=r)
                child.log_metrics({"n_pairs": 10.0 * (r + 1)})
                children.append(child.run_id)
        run.log_metrics({"best_val_iou": 1.5})
        with pytest.raises(ValueError):
            with run.nested("round_bad") as bad:
                raise ValueError("bad round")
    parent = client.get_run(run.run_id)
    assert parent.info.status == "FINISHED"
    assert parent.data.metrics == {"best_val_iou": 1.5}
    for r, cid in enumerate(children):
        child = client.get_run(cid)
        assert child.info.status == "FINISHED"
        assert child.data.tags["mlflow.parentRunId"] == run.run_id
        assert child.info.experiment_id == parent.info.experiment_id   # found by the same experiment search
        assert child.data.tags["plad.round"] == str(r) and child.data.tags["plad.method"] == "plad"
        assert child.data.metrics == {"val_iou": 0.5 + r, "n_pairs": 10.0 * (r + 1)}
    assert client.get_run(bad.run_id).info.status == "FAILED"


def test_log_model_register_champion_predict(store, client, tmp_path, capsys, tiny_checkpoint):
    import torch

    from plad.domains import get_domain
    from plad.domains.base import pad_programs

    domain = get_domain("csg2d")
    ckpt = tiny_checkpoint(tmp_path / "model.pt", "csg2d")
    name = "plad-test-csg2d"
    with StageRun("finetune", "csg2d", {}, tmp_path / "run", method="plad") as run:
        uri = run.log_model(ckpt, registered_name=name, beam=3)
    assert uri.startswith(f"models:/{name}/")
    version = uri.rsplit("/", 1)[1]
    mv = client.get_model_version(name, version)
    assert mv.run_id == run.run_id
    tracking.set_champion(name, version)
    assert str(client.get_model_version_by_alias(name, "champion").version) == version

    client.set_model_version_tag(name, version, "plad.method", "lest_st")
    client.set_model_version_tag(name, version, "plad.test", "0.9")
    row = next(r for r in tracking.registered_models() if r["name"] == name)
    assert row["aliases"] == ["champion"] and row["method"] == "lest_st" and row["test"] == "0.9"
    from plad.serve.cli import main as plad_main
    assert plad_main(["models"]) == 0
    listed = capsys.readouterr().out
    assert name in listed and "champion" in listed and "lest_st" in listed

    loaded = tracking.load_registered(f"models:/{name}@champion")
    rng = np.random.default_rng(0)
    shapes = rng.random((2, *domain.shape)) < 0.3
    out = loaded.predict(shapes)
    metric = domain.metric.name
    assert list(out.columns) == ["program", metric, "error"] and len(out) == 2 and out["error"].isna().all()
    ids = [domain.parse(text) for text in out["program"]]
    executed = domain.execute(pad_programs(ids))
    expected = domain.metric(executed, torch.from_numpy(shapes)).numpy()
    np.testing.assert_allclose(out[metric].to_numpy(), expected, rtol=1e-6, atol=1e-9)

    # uint8 input and a beam override through params
    out1 = loaded.predict(shapes.astype(np.uint8), params={"beam": 1})
    assert len(out1) == 2 and all(domain.parse(t) for t in out1["program"])
    # a one-column DataFrame of arrays gives the same answer as the ndarray
    import pandas as pd

    frame = loaded.predict(pd.DataFrame({"shape": list(shapes)}))
    assert list(frame["program"]) == list(out["program"])

    # a fresh process (as a server would) loads the model from its code and agrees
    np.save(tmp_path / "shapes.npy", shapes)
    script = textwrap.dedent(f"""
        import json, numpy as np
        from plad.tracking import load_registered
        out = load_registered("models:/{name}@champion").predict(np.load({str(tmp_path / "shapes.npy")!r}))
        print(json.dumps(list(out["program"])))
    """)
    fresh = subprocess.run([sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True,
                           text=True, env=os.environ.copy())
    assert fresh.returncode == 0, fresh.stderr
    assert json.loads(fresh.stdout.strip().splitlines()[-1]) == list(out["program"])


#: load a pyfunc model and predict, in a process of its own that has imported nothing of plad
FRESH_PREDICT = """
import json, sys
import mlflow.pyfunc, numpy as np
out = mlflow.pyfunc.load_model(sys.argv[1]).predict(np.load(sys.argv[2]))
print(json.dumps({"program": list(out["program"]), "value": [float(v) for v in out.iloc[:, 1]]}))
"""


def predict_in_fresh_process(uri: str, shapes: np.ndarray, folder) -> dict:
    np.save(folder / "shapes.npy", shapes)
    fresh = subprocess.run([sys.executable, "-c", FRESH_PREDICT, uri, str(folder / "shapes.npy")], cwd=REPO_ROOT,
                           capture_output=True, text=True, env=os.environ.copy())
    assert fresh.returncode == 0, fresh.stderr[-3000:]
    return json.loads(fresh.stdout.strip().splitlines()[-1])


def test_a_logged_model_is_code_and_loads_in_a_fresh_process(store, tmp_path, tiny_checkpoint):
    """Models from code: the logged model holds ``pyfunc_model.py`` (which reaches the package through
    ``plad.tracking.serving.Predictor`` alone), no pickle; a new process loads it by its URI and predicts
    what the checkpoint predicts."""
    import ast

    import mlflow
    import yaml

    from plad.tracking.serving import Predictor

    ckpt = tiny_checkpoint(tmp_path / "model.pt", "csg3d", seed=1)
    with StageRun("finetune", "csg3d", {}, tmp_path / "run", method="plad") as run:
        uri = run.log_model(ckpt, beam=2)
    local = tmp_path / "downloaded"
    mlflow.artifacts.download_artifacts(uri, dst_path=str(local))
    flavor = yaml.safe_load((local / "MLmodel").read_text())["flavors"]["python_function"]
    assert flavor["loader_module"] == "mlflow.pyfunc.loaders.code_model" and flavor["config"] == {"beam": 2}
    assert "python_model" not in flavor and not (local / "python_model.pkl").exists()
    code = (local / "pyfunc_model.py").read_text()
    imported = {node.module for node in ast.walk(ast.parse(code)) if isinstance(node, ast.ImportFrom)}
    assert {m for m in imported if m.split(".")[0] == "plad"} == {"plad.tracking.serving"}

    shapes = np.random.default_rng(1).random((2, 32, 32, 32)) < 0.2
    expected = Predictor(ckpt, beam=2).predict(shapes)
    got = predict_in_fresh_process(uri, shapes, tmp_path)
    assert got["program"] == list(expected["program"])
    np.testing.assert_allclose(got["value"], expected["iou"].to_numpy(), rtol=1e-6)


@pytest.mark.filterwarnings("ignore:.*An input example was not provided")
def test_a_model_logged_as_a_pickle_still_loads(store, tmp_path, tiny_checkpoint):
    """Models logged before models from code are a pickled ``plad.tracking.PladPyfuncModel`` (by reference:
    its name and its attributes); the same pickle, made here by MLflow as it was then, still loads."""
    import mlflow

    from plad.tracking.serving import Predictor, _model_arguments

    ckpt = tiny_checkpoint(tmp_path / "model.pt", "csg2d", seed=2)
    old = tmp_path / "old-model"
    arguments = _model_arguments(ckpt, beam=3)    # as logged then: no model config, the instance itself
    del arguments["model_config"]
    mlflow.pyfunc.save_model(str(old), **{**arguments, "python_model": tracking.PladPyfuncModel(beam=3)})
    pickled = (old / "python_model.pkl").read_bytes()
    assert b"plad.tracking" in pickled and b"PladPyfuncModel" in pickled and b"load_context" not in pickled
    shapes = np.random.default_rng(2).random((3, 64, 64)) < 0.3
    expected = Predictor(ckpt, beam=3).predict(shapes)
    got = predict_in_fresh_process(str(old), shapes, tmp_path)
    assert got["program"] == list(expected["program"])
    np.testing.assert_allclose(got["value"], expected["chamfer"].to_numpy(), rtol=1e-6)


def test_a_stage_records_the_params_file_it_read(store, client, tmp_path, monkeypatch, tiny_checkpoint):
    """``--params`` elsewhere than ./params.yaml: the run's tags come from that file (and its profile's)."""
    from plad.data.files import write_prepared
    from plad.layout import Layout
    from plad.stages import evaluate

    layout = Layout(tmp_path / "project")
    rng = np.random.default_rng(0)
    splits = {s: rng.random((3, 64, 64)) < 0.3 for s in ("train", "val", "test")}
    write_prepared("csg2d", (64, 64), splits, layout.prepared("csg2d"), layout.prepared_summary("csg2d"))
    tiny_checkpoint(layout.model("csg2d"), "csg2d")
    params = tmp_path / "elsewhere" / "other.yaml"
    (params.parent / "profiles").mkdir(parents=True)
    params.write_text("profile: tiny\nevaluate:\n  base: {beam: 1, batch_size: 3, grid_shapes: 2}\n  csg2d: {}\n")
    (params.parent / "profiles" / "tiny.yaml").write_text("evaluate:\n  base: {beam: 2}\n")
    monkeypatch.chdir(tmp_path)   # ./params.yaml does not exist here
    assert evaluate.main(["--params", str(params), "--section", "evaluate.csg2d", "--root", str(layout.root)]) == 0
    run_id = json.loads((layout.eval_dir("sp", "csg2d") / "mlflow_run.json").read_text())["run_id"]
    run = client.get_run(run_id)
    assert run.data.tags["plad.profile"] == "tiny" and run.data.params["beam"] == "2"
    assert run.data.tags["plad.pipeline"] == pipeline_tags(params)["plad.pipeline"] != pipeline_tags("none.yaml")[
        "plad.pipeline"]
