"""A fast CLI start: `plad --help`, `plad models`, `plad data check` and argument errors import
neither torch, MLflow nor open3d (each run in a fresh interpreter, its sys.modules inspected)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT as REPO

HEAVY = ("torch", "mlflow", "open3d")

PROBE = """
import json, sys
from plad.serve.cli import main
try:
    status = main(sys.argv[1:])
except SystemExit as exc:
    status = exc.code
print(json.dumps({"status": status, "heavy": sorted({m.split(".")[0] for m in sys.modules} & set(HEAVY))}),
      file=sys.stderr)
""".replace("HEAVY", repr(HEAVY))


def probe(*args: str, cwd: Path, env: dict[str, str] | None = None) -> tuple[int, list[str], str]:
    full = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    full.update(env or {}, PYTHONPATH=str(REPO))
    res = subprocess.run([sys.executable, "-c", PROBE, *args], cwd=cwd, env=full, capture_output=True, text=True,
                         timeout=300)
    last = json.loads(res.stderr.strip().splitlines()[-1])
    return last["status"], last["heavy"], res.stdout + res.stderr


@pytest.mark.parametrize("args", [
    ("--help",), ("infer", "--help"), ("models", "ship", "--help"),
    ("infer", "nodomain", "x.png"), ("execute",), ("models", "ship", "csg2d"), ("data", "nocheck"),
])
def test_help_and_argument_errors_import_nothing_heavy(args, tmp_path):
    status, heavy, out = probe(*args, cwd=tmp_path)
    assert status in (0, 2), out
    assert heavy == [], f"plad {' '.join(args)} imported {heavy}"


def test_models_imports_nothing_heavy_and_creates_nothing(tmp_path):
    status, heavy, out = probe("models", cwd=tmp_path, env={"PLAD_SHIPPED_DIR": str(REPO / "plad" / "shipped")})
    assert status == 0 and heavy == [], out
    assert "domain" in out and "none configured" in out
    assert list(tmp_path.iterdir()) == []


def test_data_check_covers_every_domain_and_imports_nothing_heavy(tmp_path, datasets_dir):
    from plad.data.datasets import CHECKS
    from plad.domains import domain_names, get_domain

    # every domain's real shapes come from a source that `plad data check` checks
    assert {get_domain(d).targets.name for d in domain_names()} <= set(CHECKS)
    status, heavy, out = probe("data", "check", cwd=tmp_path, env={"PLAD_DATA_DIR": str(datasets_dir)})
    assert heavy == [], out
    assert status == 0, out
    assert "CAD test: 3000 shapes (64, 64)" in out and "11922 programs" in out
    assert "train: 10536 programs, val: 693 programs, test: 693 programs" in out


def test_the_startup_benchmark_prints_the_ratio():
    res = subprocess.run([sys.executable, "-m", "bench.startup", "--repeats", "2"], cwd=REPO,
                         env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    last = res.stdout.strip().splitlines()[-1]
    assert last.startswith("ratio ") and float(last.split()[1]) > 0
