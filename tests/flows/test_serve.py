"""The periodic-retraining recipe of docs/pipeline.md on real processes: `prefect server start`, the flow
served with `python -m flows.finetune --serve`, and a retraining that picks up new shapes once they are prepared.

New shapes reach a flow run through the prepared file of its layout root (what `python -m
flows.prepare_data` or `dvc repro prepare` writes); here the prepared 2D file is rewritten with more
training shapes between two runs of the served deployment, and the second run trains on them.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest

from plad.data.files import load_prepared, write_prepared
from plad.layout import Layout
from tests.procs import child_env, children, free_port, left_behind, start, stop, tail, wait_http
from tests.tiny import csg2d_inputs

pytestmark = pytest.mark.integration

PARAMS = """
domains: [csg2d]
finetune:
  csg2d:
    device: cpu
    threads: 1
    val_limit: 6
    methods:
      st: {method: st}
    plad:
      infer_beam: 2
      infer_batch: 10
      val_beam_epoch: 1
      val_beam_round: 1
      max_rounds: 1
      train: {batch_size: 4, steps_per_epoch: 2, max_epochs: 1, patience: 3}
evaluate:
  csg2d: {}
report:
  per_round: {}
flows:
  methods: [st]
  shards: 2
  retry_delay_seconds: 0
  threads_per_task: 1
  evaluate: false
"""


def prepare(root: Path, train_shapes: int, full: dict) -> None:
    """The root's prepared 2D file with the first ``train_shapes`` training shapes (as a prepare step writes it)."""
    layout = Layout(root)
    write_prepared("csg2d", (64, 64), {"train": full["train"][:train_shapes], "val": full["val"][:6],
                                       "test": full["test"][:6]},
                   layout.prepared("csg2d"), layout.prepared_summary("csg2d"))


def test_the_served_deployment_retrains_on_newly_prepared_shapes(tmp_path, datasets_dir):
    from prefect.client.orchestration import get_client
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    root = csg2d_inputs(tmp_path / "project", datasets_dir)
    full = {s: load_prepared(Layout(root).prepared("csg2d"), s) for s in ("train", "val", "test")}
    prepare(root, 8, full)
    (tmp_path / "params.yaml").write_text(PARAMS)
    before = children()
    port = free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = child_env(PREFECT_HOME=str(tmp_path / "prefect"), PREFECT_API_URL=api,
                    MLFLOW_TRACKING_URI=f"sqlite:///{tmp_path / 'mlflow.db'}")
    server_log, serve_log = tmp_path / "server.log", tmp_path / "serve.log"
    server = start([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
                   env, server_log)
    served = None
    try:
        wait_http(f"http://127.0.0.1:{port}/api/health", server, server_log, timeout=180)
        served = start([sys.executable, "-m", "flows.finetune", "--params", str(tmp_path / "params.yaml"),
                        "--root", str(root), "--serve"], env, serve_log, cwd=tmp_path)
        with temporary_settings({PREFECT_API_URL: api}):
            deadline = time.monotonic() + 180
            while True:   # the serving process registers the deployment, then polls for runs
                with get_client(sync_client=True) as client:
                    try:
                        deployment = client.read_deployment_by_name("plad-finetune/plad-retrain")
                        break
                    except Exception:
                        assert served.poll() is None and time.monotonic() < deadline, tail(serve_log)
                time.sleep(2)
            assert deployment.schedules, "the served deployment has no schedule (flows.cron)"
            summaries = {}
            for week, shapes in (("week1", 8), ("week2", 12)):
                if week == "week2":
                    prepare(root, shapes, full)   # new shapes arrive and are prepared
                run = run_deployment("plad-finetune/plad-retrain", parameters={"run_name": week}, timeout=400)
                assert run.state.is_completed(), f"{run.state}\n{tail(serve_log)}"
                path = Layout(root).flow_run(week).finetune_summary("csg2d", "st")
                summaries[week] = json.loads(path.read_text())
    finally:
        if served is not None:
            stop(served)
        stop(server)
    assert summaries["week1"]["train_shapes"] == 8
    assert summaries["week2"]["train_shapes"] == 12      # the retraining picked up the new shapes
    assert left_behind(before) == []
