"""The fine-tuning flow on real orchestration processes: a Prefect server, a Dask cluster, a process worker.

Everything runs on loopback and is started here, each in a process group of
its own; every test stops what it started (also when it fails: fixtures with
finalizers) and checks that no process is left behind. Process-based runners
need a real Prefect server (the temporary one would start a server per
worker), so the module starts ``prefect server start`` once.
"""
from __future__ import annotations

import json
import os
import signal
import sqlite3
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from plad.layout import Layout
from tests.procs import child_env, children, free_port, group, left_behind, start, stop, tail, wait_http

pytestmark = pytest.mark.integration

#: the shapes of one round and its shards: enough work per shard to kill a worker while it runs one
TRAIN_SHAPES, SHARDS = 120, 4
#: the training shapes of the work-pool run, set by a profile
FEWER_SHAPES = 12

PARAMS = """
domains: [csg2d]
finetune:
  csg2d:
    device: cpu
    threads: 1
    train_limit: {train}
    val_limit: 6
    methods:
      st: {{method: st}}
    plad:
      infer_beam: 3
      infer_batch: 10
      val_beam_epoch: 1
      val_beam_round: 1
      max_rounds: 1
      train: {{batch_size: 8, steps_per_epoch: 2, max_epochs: 1, patience: 3}}
evaluate:
  csg2d: {{}}
report:
  per_round: {{}}
flows:
  methods: [st]
  shards: {shards}
  retry_delay_seconds: 0
  threads_per_task: 1
  dask_address: {dask}
  evaluate: false
"""


@pytest.fixture(scope="module")
def smoke(csg2d_project) -> Path:
    """The layout root of a project with the prepared 2D shapes and a tiny pretrained model (random weights);
    each flow run writes under its ``runs/flows/<run name>/``."""
    return csg2d_project


def params(out: Path, dask: str | None = None) -> Path:
    """A params file in ``out`` for the flow."""
    dest = out / "params.yaml"
    dest.write_text(PARAMS.format(train=TRAIN_SHAPES, shards=SHARDS, dask=dask or "null"))
    return dest


@pytest.fixture(scope="module")
def prefect_server(tmp_path_factory):
    """``prefect server start`` on a free loopback port: (API URL, the environment its clients need)."""
    home = tmp_path_factory.mktemp("prefect")
    port = free_port()
    env = child_env(PREFECT_HOME=str(home), PREFECT_API_URL=f"http://127.0.0.1:{port}/api")
    log = home / "server.log"
    server = start([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
                   env, log)
    try:
        wait_http(f"http://127.0.0.1:{port}/api/health", server, log, timeout=150)
        yield env["PREFECT_API_URL"], env
    finally:
        stop(server)
        assert group(server.pid) == [], "the Prefect server left processes"


def flow_task_runs(api_url: str, run_name: str) -> list[tuple[str, str]]:
    """(task run name, state) of the flow run that wrote ``run_name``."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings({PREFECT_API_URL: api_url}), get_client(sync_client=True) as client:
        runs = [r for r in client.read_flow_runs() if (r.parameters or {}).get("run_name") == run_name]
        assert len(runs) == 1, runs
        tasks = client.read_task_runs(flow_run_filter=FlowRunFilter(id={"any_": [runs[0].id]}))
        return [(t.name, t.state_name) for t in tasks]


def one_process_pbest(root: Path):
    """What round 1 puts in P_BEST, inferred in this process: best-of-beam programs and values."""
    from plad.data.files import evenly_spaced, load_prepared
    from plad.domains import get_domain
    from plad.model.checkpoint import load_model
    from plad.model.decode import infer_batched

    layout = Layout(root)
    model, _ = load_model(layout.model("csg2d"))
    train = evenly_spaced(load_prepared(layout.prepared("csg2d"), "train"), TRAIN_SHAPES)   # as train_limit picks
    return infer_batched(model, get_domain("csg2d"), train, 3, 10)


def mlflow_runs(db: Path) -> list[tuple[str, str]]:
    with sqlite3.connect(db) as c:
        return list(c.execute("select name, status from runs order by start_time"))


def _executing(dask_worker) -> list[str]:   # runs inside a Dask worker (client.run)
    return [str(ts.key) for ts in dask_worker.state.executing]


def test_round_inference_on_a_dask_cluster_survives_a_killed_worker(prefect_server, smoke, tmp_path):
    from distributed import Client

    from plad.domains import get_domain
    from plad.learn.pbest import PBest

    api_url, server_env = prefect_server
    before = children()
    env = {**server_env, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = {"scheduler": start([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                 "--port", str(port), "--no-dashboard"], env, tmp_path / "scheduler.log")}
    client = None
    try:
        for name in ("w1", "w2"):
            procs[name] = start([sys.executable, "-m", "distributed.cli.dask_worker", address, "--name", name,
                                 "--nworkers", "1", "--nthreads", "1", "--no-dashboard"], env, tmp_path / f"{name}.log")
        client = Client(address, timeout=60)
        client.wait_for_workers(2, timeout=120)
        victim = next(a for a, w in client.scheduler_info()["workers"].items() if w["name"] == "w1")
        flow_log = tmp_path / "flow.log"
        procs["flow"] = start([sys.executable, "-m", "flows.finetune", "--params", str(params(tmp_path, address)),
                               "--root", str(smoke), "--run-name", "killed"], env, flow_log, cwd=tmp_path)
        # kill worker w1 (its nanny and worker process) while it executes an inference shard
        killed: list[str] = []
        deadline = time.monotonic() + 240
        while not killed and procs["flow"].poll() is None and time.monotonic() < deadline:
            running = client.run(_executing, workers=[victim]).get(victim, [])
            if any("infer_shard" in key for key in running):
                os.killpg(procs["w1"].pid, signal.SIGKILL)   # a crash: no goodbye to the scheduler
                killed = running
            time.sleep(0.05)
        assert killed, f"w1 never ran a shard:\n{tail(flow_log)}"
        status = procs["flow"].wait(timeout=max(10.0, deadline - time.monotonic()))
        assert status == 0, tail(flow_log)
    finally:
        if client is not None:
            client.close()
        for proc in procs.values():
            stop(proc)
    assert left_behind(before) == []

    # nothing lost: every shard completed (the killed one again, on w2), and P_BEST is one process's
    shards = [state for name, state in flow_task_runs(api_url, "killed") if name.startswith("infer shard")]
    assert shards == ["Completed"] * SHARDS
    values, programs, _ = one_process_pbest(smoke)
    pbest = PBest.load(Layout(smoke).flow_run("killed").finetune_dir("csg2d", "st") / "pbest.npz",
                       get_domain("csg2d").metric)
    canonical = [get_domain("csg2d").canonical(p) for p in programs]   # P_BEST stores canonical forms
    assert pbest.has.all() and [pbest.program(i) for i in range(TRAIN_SHAPES)] == canonical
    assert np.allclose(pbest.values, values, atol=1e-9)


def test_deployment_on_a_work_pool_runs_on_a_process_worker(prefect_server, smoke, tmp_path):
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.deploy import deploy

    api_url, server_env = prefect_server
    before = children()
    db = tmp_path / "mlflow.db"
    # a profile beside the params file: fewer training shapes, chosen by the deployment
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "fewer.yaml").write_text(f"finetune:\n  csg2d:\n    train_limit: {FEWER_SHAPES}\n")
    with temporary_settings({PREFECT_API_URL: api_url}):
        # the run's MLflow store comes with the deployment (job variables), as a team's tracking server would
        deploy("plad-test", "smoke", params_path=str(params(tmp_path)), profile="fewer", methods=["st"],
               root=str(smoke), env={"MLFLOW_TRACKING_URI": f"sqlite:///{db}"})
    # the worker runs in a folder of its own: the deployment's pull step sets the repository as working directory
    (tmp_path / "worker").mkdir()
    log = tmp_path / "worker.log"
    worker = start([sys.executable, "-m", "prefect", "worker", "start", "--pool", "plad-test"],
                   {**server_env, "PREFECT_WORKER_QUERY_SECONDS": "1"}, log, cwd=tmp_path / "worker")
    try:
        with temporary_settings({PREFECT_API_URL: api_url}):
            run = run_deployment("plad-finetune/smoke", parameters={"run_name": "smoke"}, timeout=300)
        assert run.state.is_completed(), f"{run.state}\n{tail(log)}"
    finally:
        stop(worker)
    assert left_behind(before) == []
    runs = mlflow_runs(db)   # the stage run and the row run of (profile, csg2d, st) it nests under
    assert ("finetune", "FINISHED") in runs and ("st", "FINISHED") in runs
    summary = Layout(smoke).flow_run("smoke").finetune_summary("csg2d", "st")
    assert summary.exists(), tail(log)
    assert json.loads(summary.read_text())["train_shapes"] == FEWER_SHAPES   # the profile was applied
