"""Prefect flows run the same functions as the DVC stages.

Marked ``pipeline``: the flows run whole stage pipelines (prepare on every domain; rounds, evaluation and
the report) under a temporary Prefect server, about 3 minutes of the suite.
"""
import json

import numpy as np
import pytest

from plad.layout import Layout

pytestmark = pytest.mark.pipeline


@pytest.fixture(scope="module")
def prefect_harness(tmp_path_factory):
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


def test_prepare_flow_matches_the_stage(tmp_path, datasets_dir, prefect_harness):
    from flows.prepare_data import prepare_data
    from plad.data.files import load_prepared

    params = tmp_path / "params.yaml"
    params.write_text(f"domains: [csg2d, csg3d, shapeassembly]\n"
                      f"prepare:\n  data_dir: {datasets_dir}\n  limit: {{partnet: 3}}\n")
    result = prepare_data(str(params), str(tmp_path))
    out = tmp_path / "data" / "prepared"
    assert result["domains"]["csg2d"]["val_count"] == 3000
    assert result["sources"]["partnet"]["listed"] == {"train": 3, "val": 3, "test": 3}
    for domain in ("csg2d", "csg3d", "shapeassembly"):
        assert json.loads((out / f"{domain}.json").read_text()) == result["domains"][domain]
    assert load_prepared(out / "csg2d.npz", "val").shape == (3000, 64, 64)
    # one PartNet build (one task) feeds both 3D domains
    assert np.array_equal(load_prepared(out / "csg3d.npz", "test"), load_prepared(out / "shapeassembly.npz", "test"))


SMOKE_PARAMS = """
domains: [csg2d]
finetune:
  csg2d:
    train_limit: 24
    val_limit: 6
    max_minutes: 5
    methods:
      lest_st_ws: {method: lest+st+ws}
      st: {method: st}
    plad:
      infer_beam: 2
      infer_batch: 12
      val_beam_epoch: 1
      val_beam_round: 2
      max_rounds: 2
      train: {batch_size: 8, steps_per_epoch: 2, max_epochs: 1, patience: 3}
      ws: {latent: 4, hidden: 8, batch_size: 8, max_epochs: 1, sample_batch: 32}
evaluate:
  csg2d:
    limit: 6
    beam: 2
report:
  per_round: {}
flows:
  methods: [lest_st_ws]
  shards: 3
  threads_per_task: 1
  cron: "*/30 * * * *"
  deployment: plad-retrain-test
"""


@pytest.fixture(scope="module")
def smoke_params(csg2d_project):
    params = csg2d_project / "params.yaml"
    params.write_text(SMOKE_PARAMS)
    return params


def test_retraining_schedule_is_defined_by_the_params(smoke_params):
    from flows.finetune import deployment

    dep = deployment(str(smoke_params), str(smoke_params.parent))
    assert dep.name == "plad-retrain-test"
    assert [s.schedule.cron for s in dep.schedules] == ["*/30 * * * *"]
    assert dep.parameters == {"params_path": str(smoke_params.resolve()), "root": str(smoke_params.parent.resolve())}
    # a profile applies to the deployment itself (its cron here) and is passed on to every run it starts
    profiles = smoke_params.parent / "profiles"
    profiles.mkdir(exist_ok=True)
    (profiles / "hourly.yaml").write_text('flows:\n  cron: "0 * * * *"\n')
    dep = deployment(str(smoke_params), str(smoke_params.parent), profile="hourly")
    assert [s.schedule.cron for s in dep.schedules] == ["0 * * * *"]
    assert dep.parameters["profile"] == "hourly"


def test_sharded_inference_equals_one_batch(smoke_params):
    from flows.finetune import _infer_shard
    from plad.data.files import load_prepared
    from plad.domains import get_domain
    from plad.model.checkpoint import load_model
    from plad.model.decode import infer_batched

    layout = Layout(smoke_params.parent)
    model, _ = load_model(layout.model("csg2d"))
    shapes = load_prepared(layout.prepared("csg2d"), "val")[:10]
    whole = infer_batched(model, get_domain("csg2d"), shapes, 2, 10)
    parts = [_infer_shard(model, "csg2d", shapes[i:i + 4], 2, 10, None) for i in range(0, 10, 4)]
    assert np.allclose(whole[0], np.concatenate([p[0] for p in parts]), atol=1e-9)
    assert np.array_equal(whole[2], np.concatenate([p[2] for p in parts]))


def test_finetune_flow_runs_rounds_as_tasks_and_reports(smoke_params, prefect_harness, tmp_path, monkeypatch):
    from prefect.client.orchestration import get_client

    from flows.finetune import finetune_flow

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    out = finetune_flow(str(smoke_params), run_name="once", root=str(smoke_params.parent))
    run = Layout(smoke_params.parent).flow_run("once")
    assert run.root == smoke_params.parent / "runs" / "flows" / "once" and out["out_dir"] == str(run.root)
    summary = out["methods"]["lest_st_ws"]
    assert summary["units"] == 2 and np.isfinite(summary["test"])
    assert (run.finetune_dir("csg2d", "lest_st_ws") / "ws_round_002.npz").exists()
    assert (run.eval_dir("sp", "csg2d") / "metrics.json").exists()
    table = (run.results_dir / "table.md").read_text()
    assert "| LEST+ST+WS |" in table and "| SP |" in table
    with get_client(sync_client=True) as client:
        names = [t.name for t in client.read_task_runs()]
    shards = [n for n in names if n.startswith("infer shard")]
    assert len(shards) == 2 * 3  # 2 rounds x 3 shards
    for step in ["train", "validate", "wake-sleep generator", "infer"]:
        assert any(n.startswith(f"round 1: {step}") for n in names), step
