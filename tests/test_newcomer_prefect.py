"""The project's Prefect defaults (flows/__init__.py): a plain offline flow run, with none of Prefect's
settings in the environment, prints no traceback and no telemetry failure, and a value set in the
environment still wins."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

FLOW = """
import flows   # the project's defaults, as `python -m flows.<name>` sets them
from prefect import flow, task

@task
def double(x):
    return 2 * x

@flow
def plain():
    return sum(double.map([1, 2, 3]).result())

print("result", plain())
"""


def test_a_plain_offline_flow_run_prints_no_traceback(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_") and k != "DO_NOT_TRACK"}
    env.update(PYTHONPATH=str(REPO), PREFECT_HOME=str(tmp_path / "prefect"),
               HTTPS_PROXY="http://127.0.0.1:9", HTTP_PROXY="http://127.0.0.1:9")   # offline: nothing gets out
    env["NO_PROXY"] = env["no_proxy"] = "127.0.0.1,localhost"   # the temporary server is on loopback
    res = subprocess.run([sys.executable, "-c", FLOW], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr
    assert "result 12" in res.stdout
    for phrase in ("Traceback", "database is locked", "Failed to send telemetry", "ERROR"):
        assert phrase not in res.stderr, res.stderr


def test_the_environment_wins_over_the_defaults(tmp_path):
    code = ("import os, flows; "
            "print(os.environ['PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS'], os.environ['DO_NOT_TRACK'])")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_") and k != "DO_NOT_TRACK"}
    env.update(PYTHONPATH=str(REPO), PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="300")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["300", "1"]


def test_serve_without_a_server_is_a_one_line_error(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PYTHONPATH=str(REPO), PREFECT_HOME=str(tmp_path / "prefect"))
    res = subprocess.run([sys.executable, "-m", "flows.finetune", "--params", str(REPO / "params.yaml"), "--serve"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "--serve needs a running Prefect server" in res.stderr and "PREFECT_API_URL" in res.stderr
    assert "Starting temporary server" not in res.stderr
