"""The champion alias only moves to a better model; a rebuilt report registers only when asked (issue 18)."""
from __future__ import annotations

import json

import pytest
import torch

from plad.domains import get_domain
from plad.layout import Layout
from plad.model.checkpoint import save_checkpoint
from plad.model.network import ModelConfig, PLADNet

NAME = "plad-csg2d"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("mlflow")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mp.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    mp.setenv("PLAD_PIPELINE_ID", "trust-champion")
    import mlflow

    mlflow.set_tracking_uri(uri)
    mlflow.MlflowClient().search_experiments()
    yield uri
    while mlflow.active_run() is not None:
        mlflow.end_run()
    mp.undo()


@pytest.fixture(scope="module")
def pipeline(store, tmp_path_factory):
    """A root with SP and WS checkpoints and their MLflow runs: WS's validation history (chamfer, lower is
    better) is the issue's [(1, 4.185), (2, 5.682), (0, 4.185)]: best 4.185, last step 5.682."""
    from plad.tracking import StageRun

    root = tmp_path_factory.mktemp("root")
    layout = Layout(root)
    d = get_domain("csg2d")
    torch.manual_seed(0)
    model = PLADNet(ModelConfig(vocab_size=len(d.tokens), max_len=d.tokens.max_len, input_shape=d.shape,
                                enc_channels=(4, 8, 8, 8), d_model=32, n_layers=1, n_heads=2, dim_ff=32))
    for key in ("sp", "ws"):
        layout.model("csg2d", key).parent.mkdir(parents=True, exist_ok=True)
        save_checkpoint(layout.model("csg2d", key), model, "csg2d", d.tokens.names)
        with StageRun("evaluate", "csg2d", {}, root / f"ev-{key}", method=key) as run:
            run.log_metrics({"test_chamfer": 4.5 if key == "ws" else 6.0})
    with StageRun("finetune", "csg2d", {}, root / "ft-ws", method="ws") as run:
        run.log_metrics({"val": 4.185}, step=1)
        run.log_metrics({"val": 5.682}, step=2)
        run.log_metrics({"val_at_seconds": 6.5}, step=0)
        run.log_metrics({"val_at_seconds": 4.185}, step=10)
        run.log_metrics({"val_at_seconds": 5.682}, step=20)
        run.log_metrics({"val": 4.185, "units": 2.0, "train_seconds": 20.0})
        run.set_tags({"plad.stopped": "max_rounds"})
    params = root / "params.yaml"
    params.write_text("domains: [csg2d]\nreport:\n  methods: [sp, ws]\n  per_round: {}\n")
    return root, params


def _versions():
    import mlflow

    try:
        return sorted(int(v.version) for v in mlflow.MlflowClient().search_model_versions(f"name = '{NAME}'"))
    except Exception:
        return []


def _report(pipeline, *extra):
    from plad.stages.report import main

    root, params = pipeline
    return main(["--params", str(params), "--set", "source=mlflow", "--root", str(root), *extra])


def test_from_mlflow_reads_the_best_validation_not_the_last_step(pipeline):
    from plad.eval.report import from_mlflow

    ws = {r.key: r for r in from_mlflow("csg2d", ["sp", "ws"])}["ws"]
    assert ws.val_best == pytest.approx(4.185)


def test_rebuilding_the_report_registers_nothing_unless_asked(pipeline, capsys):
    before = _versions()
    assert _report(pipeline) == 0
    assert _versions() == before
    assert "registered" not in capsys.readouterr().err


def test_champion_moves_only_to_a_better_best_validation(pipeline, capsys):
    import mlflow

    from plad.tracking import set_champion, set_version_tags

    client = mlflow.MlflowClient()
    # first registration: no champion yet -> ws (best 4.185, beating SP's 6.5)
    assert _report(pipeline, "--register") == 0
    err = capsys.readouterr().err
    first = client.get_model_version_by_alias(NAME, "champion")
    assert f"registered {NAME} version {first.version} (ws, validation chamfer 4.185)" in err
    assert float(first.tags["plad.val"]) == pytest.approx(4.185) and first.tags["plad.method"] == "ws"
    # a champion that is better (3.9 < 4.185): kept, and no new version is registered
    set_version_tags(NAME, first.version, {"plad.val": "3.9"})
    count = len(_versions())
    assert _report(pipeline, "--register") == 0
    err = capsys.readouterr().err
    assert f"kept {NAME}@champion (version {first.version}, validation chamfer 3.9)" in err
    assert len(_versions()) == count
    root, _ = pipeline
    champion = json.loads((Layout(root).results_dir / "report.json").read_text())["domains"]["csg2d"]["champion"]
    assert champion["registered"] is False
    assert champion["held"] == {"model": f"models:/{NAME}@champion", "version": str(first.version), "val": 3.9}
    assert client.get_model_version_by_alias(NAME, "champion").version == first.version
    # a worse champion (5.0): replaced by the new version
    set_version_tags(NAME, first.version, {"plad.val": "5.0"})
    set_champion(NAME, first.version)
    assert _report(pipeline, "--register") == 0
    err = capsys.readouterr().err
    now = client.get_model_version_by_alias(NAME, "champion")
    assert int(now.version) == int(first.version) + 1
    assert f"replacing version {first.version} (5)" in err


def test_a_missing_experiment_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    from plad.data.files import DataError
    from plad.eval.report import from_mlflow
    from plad.stages.report import main

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'empty.db'}")
    with pytest.raises(DataError, match="no MLflow experiment"):   # was a bare LookupError
        from_mlflow("csg2d", ["sp"])
    params = tmp_path / "params.yaml"
    params.write_text("domains: [csg2d]\nreport:\n  methods: [sp]\n  per_round: {}\n")
    assert main(["--params", str(params), "--set", "source=mlflow", "--root", str(tmp_path)]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if "mlflow.store.db" not in line]
    assert err == ["report: error: MLflow: no test evaluation for csg2d/sp"]


def test_a_champion_without_its_checkpoint_here_is_reported_not_registered(pipeline, capsys):
    """Rebuilding one domain's column on a machine where the others' checkpoints were never made: the report is
    written, and a domain whose best model has no checkpoint here registers nothing (it used to stop the stage
    with FileNotFoundError)."""
    import json

    root, _ = pipeline
    ws = Layout(root).model("csg2d", "ws")
    assert _report(pipeline) == 0   # registers nothing; the store is set up as for the other tests
    count = len(_versions())
    ws.rename(ws.with_suffix(".away"))
    try:
        assert _report(pipeline, "--register") == 0
    finally:
        ws.with_suffix(".away").rename(ws)
    assert f"report: {NAME}: its best model, ws, has no checkpoint here ({ws}); nothing registered" in \
        capsys.readouterr().err
    assert len(_versions()) == count
    report = json.loads((Layout(root).results_dir / "report.json").read_text())
    assert report["domains"]["csg2d"]["champion"]["registered"] is False
