"""A smoke run's models never become `plad infer`'s default (issue 54): registered by a run of the smoke profile
(a few test shapes) as the report stage registers its champion, they live under plad-<domain>-smoke, and
`plad infer` resolves to the shipped model; a champion measured on a subset of the test set that does hold
plad-<domain>@champion (a store of an earlier version) is passed over too, with the reason; a champion of the
cpu profile (the full test set) is used. `plad models` marks the model used and says why. A temporary SQLite
store and the tiny untrained network; no pipeline runs."""
from __future__ import annotations

import shutil

import pytest

from plad.serve.cli import main
from plad.shipped import shipped_dir
from tests.conftest import REPO_ROOT

NAME = "plad-csg2d"


@pytest.fixture
def store(tmp_path, monkeypatch):
    """An empty SQLite MLflow store, configured ($MLFLOW_TRACKING_URI); the working folder elsewhere."""
    import mlflow

    uri = f"sqlite:///{tmp_path / 'store' / 'mlflow.db'}"
    (tmp_path / "store").mkdir()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    monkeypatch.setenv("PLAD_PIPELINE_ID", "default-model")
    monkeypatch.delenv("PLAD_SHIPPED_DIR", raising=False)
    mlflow.set_tracking_uri(uri)
    mlflow.MlflowClient().search_experiments()   # creates the store
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    yield uri
    while mlflow.active_run() is not None:
        mlflow.end_run()


@pytest.fixture
def smoke_params(tmp_path):
    """params.yaml with the smoke profile selected (as `dvc exp run -S profile=smoke` leaves it), beside profiles/."""
    folder = tmp_path / "project"
    shutil.copytree(REPO_ROOT / "profiles", folder / "profiles")
    text = (REPO_ROOT / "params.yaml").read_text()
    assert "\nprofile: cpu\n" in text
    (folder / "params.yaml").write_text(text.replace("\nprofile: cpu\n", "\nprofile: smoke\n"))
    return folder / "params.yaml"


def register_as_the_report_does(params, checkpoint, run_dir) -> tuple[str, object]:
    """The report stage's registration of a domain's champion (plad/stages/report.py, tracked_report), in a
    stage run of the params file ``params``; returns (the version, what champion_tags found before)."""
    from plad.tracking import StageRun, champion_tags, set_champion, set_version_tags

    with StageRun("report", "csg2d", {}, run_dir, params_path=params, row="pipeline") as run:
        held = champion_tags(NAME)
        version = run.log_model(checkpoint, registered_name=NAME).rsplit("/", 1)[-1]
        set_version_tags(NAME, version, {"plad.method": "lest_st", "plad.test": 4.0, "plad.val": "4.1",
                                         "plad.metric": "chamfer"})
        set_champion(NAME, version)
    return version, held


def models_listing(capsys) -> str:
    capsys.readouterr()
    assert main(["models"]) == 0
    return capsys.readouterr().out


def test_the_params_say_which_test_set_they_evaluate(smoke_params):
    from plad.tracking.registry import evaluated_on
    from plad.tracking.runs import evaluated_test_set, pipeline_tags

    assert evaluated_test_set(REPO_ROOT / "params.yaml") == "full"
    assert evaluated_test_set(REPO_ROOT / "params.yaml") == pipeline_tags(REPO_ROOT / "params.yaml")["plad.test_set"]
    assert evaluated_test_set(smoke_params) == "subset" == pipeline_tags(smoke_params)["plad.test_set"]
    assert evaluated_test_set(smoke_params.parent / "missing.yaml") == "unknown"
    # a version registered before the tag existed: judged by its run's profile
    assert evaluated_on({"plad.profile": "cpu"}) == "full" and evaluated_on({"plad.profile": "smoke"}) == "unknown"
    assert evaluated_on({"plad.profile": "cpu", "plad.test_set": "subset"}) == "subset"


def test_a_smoke_run_registers_under_its_own_name_and_infer_keeps_the_shipped_model(
        store, smoke_params, tmp_path, tiny_checkpoint, capsys):
    import mlflow

    from plad.serve.resolve import default_model, resolve

    version, held = register_as_the_report_does(smoke_params, tiny_checkpoint(tmp_path / "smoke.pt", "csg2d"),
                                                tmp_path / "report-run")
    assert held is None
    client = mlflow.MlflowClient()
    assert [m.name for m in client.search_registered_models()] == [f"{NAME}-smoke"]
    mv = client.get_model_version_by_alias(f"{NAME}-smoke", "champion")
    assert str(mv.version) == version and mv.tags["plad.profile"] == "smoke" and mv.tags["plad.test_set"] == "subset"
    assert mv.tags["plad.method"] == "lest_st"

    choice = resolve("csg2d")
    assert choice.kind == "shipped" and choice.path == shipped_dir() / "csg2d" / "model.pt"
    assert "no champion in the MLflow store" in choice.notes[0]
    assert default_model("csg2d").kind == "shipped"

    listed = models_listing(capsys)
    smoke_row = next(line for line in listed.splitlines() if f"models:/{NAME}-smoke/{version}" in line)
    assert smoke_row.split()[:2] == ["csg2d", "registered"] and f" models:/{NAME}-smoke/" in smoke_row   # no *
    assert "profile smoke, subset test set" in listed
    assert f"*{shipped_dir() / 'csg2d' / 'model.pt'}" in listed
    assert f"plad infer csg2d uses {shipped_dir() / 'csg2d' / 'model.pt'}: the shipped model, as no champion " \
           "in the MLflow store" in listed


def test_a_champion_measured_on_a_few_shapes_is_passed_over_and_a_full_one_is_used(
        store, smoke_params, tmp_path, tiny_checkpoint, capsys):
    import mlflow

    from plad.serve.resolve import resolve
    from plad.tracking import StageRun
    from plad.tracking.serving import log_pyfunc

    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt", "csg2d")
    client = mlflow.MlflowClient()
    # a smoke model holding plad-csg2d@champion, as an earlier version registered it (no name of its own,
    # no tags on the version: its run says which profile and test set)
    with StageRun("report", "csg2d", {}, tmp_path / "old-run", params_path=smoke_params, row=None):
        old = log_pyfunc(checkpoint, registered_name=NAME).rsplit("/", 1)[-1]
    client.set_registered_model_alias(NAME, "champion", old)
    choice = resolve("csg2d")
    assert choice.kind == "shipped" and choice.path == shipped_dir() / "csg2d" / "model.pt"
    assert choice.notes == (f"models:/{NAME}@champion (version {old}, profile smoke) was evaluated on a subset of "
                            f"the test set, so it is not a default; --model models:/{NAME}@champion uses it",)
    listed = models_listing(capsys)
    assert f"*{shipped_dir() / 'csg2d' / 'model.pt'}" in listed and f"*models:/{NAME}/" not in listed
    assert "was evaluated on a subset of the test set, so it is not a default" in listed
    # named explicitly, it is still there to use
    assert resolve("csg2d", f"models:/{NAME}@champion").kind == "mlflow"

    # the cpu profile evaluates the full test set: its champion is the default
    version, held = register_as_the_report_does(REPO_ROOT / "params.yaml", checkpoint, tmp_path / "report-run")
    assert held == (int(old), {}) and int(version) == int(old) + 1   # the report compares with the held champion
    assert client.get_model_version(NAME, version).tags["plad.test_set"] == "full"
    choice = resolve("csg2d")
    assert choice.kind == "champion" and choice.ref == f"models:/{NAME}@champion" and choice.path.is_file()
    listed = models_listing(capsys)
    assert f"*models:/{NAME}/{version} @champion" in listed
    assert f"plad infer csg2d uses models:/{NAME}/{version}: models:/{NAME}@champion (version {version}, profile " \
           "cpu): the MLflow store's champion, evaluated on the full test set" in listed
