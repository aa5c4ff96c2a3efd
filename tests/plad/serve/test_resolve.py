"""Shipped models and model resolution: `plad models ship` packages the tiny 2D model (tests/tiny.py,
evaluated on 8 CAD test shapes) into a temporary shipped-models folder ($PLAD_SHIPPED_DIR); `plad infer`
uses it from any directory and creates no MLflow store there; a configured store's champion comes
first; `plad models` lists both; the pyfunc loader resolves the same way."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from plad.serve.cli import main
from tests.conftest import REPO_ROOT as REPO

PROGRAM = "c(32,32,16)s(40,40,12)-$"


@pytest.fixture(scope="module")
def trained(tmp_path_factory, datasets_dir):
    """A layout root with the tiny 2D model as the SP model and its test evaluation (8 shapes, beam 2)."""
    from plad.layout import Layout
    from plad.stages.evaluate import EvaluateConfig, evaluate
    from tests.tiny import csg2d_inputs

    root = csg2d_inputs(tmp_path_factory.mktemp("root"), datasets_dir)
    evaluate(EvaluateConfig(domain="csg2d", limit=8, beam=2, grid_shapes=4, device="cpu"), Layout(root))
    return root


@pytest.fixture(scope="module")
def shipped(trained, tmp_path_factory):
    """The folder of shipped models holding the tiny 2D one, shipped with the CLI."""
    dest = tmp_path_factory.mktemp("shipped")
    status = main(["models", "ship", "csg2d", str(trained / "runs/pretrain/csg2d/best.pt"),
                   "--metrics", str(trained / "results/eval/sp/csg2d/metrics.json"), "--root", str(trained),
                   "--params", str(REPO / "params.yaml"), "--dest", str(dest)])
    assert status == 0
    return dest


def cli(*args: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """`plad ARGS` in a fresh process with this checkout first on the path and only ``env`` changed."""
    full = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    full.update(env, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    code = "import sys; from plad.serve.cli import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, *args],
                          cwd=cwd, env=full, capture_output=True, text=True, timeout=600)


def test_ship_writes_a_small_checkpoint_and_its_sidecar(trained, shipped):
    import torch

    from plad.data.datasets.cad import CAD
    from plad.domains import get_domain
    from plad.model.checkpoint import load_model
    from plad.shipped import sha256_file, shipped_model

    model = shipped_model("csg2d", shipped)
    info = json.loads((shipped / "csg2d" / "model.json").read_text())
    assert model is not None and model.info == info
    assert info["checkpoint"]["sha256"] == sha256_file(shipped / "csg2d" / "model.pt")
    assert info["tokens"] == get_domain("csg2d").tokens.names
    metrics = json.loads((trained / "results/eval/sp/csg2d/metrics.json").read_text())
    assert info["metrics"]["mean"] == metrics["test"]["mean"] and info["metrics"]["n"] == 8
    assert info["metrics"]["metric"] == "chamfer" and info["metrics"]["higher_is_better"] is False
    prov = info["provenance"]
    assert prov["profile"] == "cpu" and "pretrain" in prov["params"] and "finetune" in prov["params"]
    assert CAD.sha256 in prov["data"]["files"].values()
    assert list(prov["data"]["prepared"]) == ["data/prepared/csg2d.npz"]
    # no path of the shipping machine: paths relative to the root or the data directory, else file names
    # (the test ships with absolute paths, the params file outside the root)
    assert prov["params_file"] == "params.yaml" and info["metrics_file"] == "results/eval/sp/csg2d/metrics.json"
    assert info["checkpoint"]["shipped_from"] == "runs/pretrain/csg2d/best.pt"

    def strings(v):
        if isinstance(v, dict):
            yield from (s for k, x in v.items() for s in (k, *strings(x)))
        elif isinstance(v, list):
            yield from (s for x in v for s in strings(x))
        elif isinstance(v, str):
            yield v
    assert not [s for s in strings(info) if s.startswith("/") or str(REPO) in s]
    # the git state a metrics file's provenance records, under the sidecar's names
    from plad.provenance import code_state
    state = code_state(str(trained))
    assert prov["git"] == {"revision": state["commit"], "dirty": state["dirty"]}
    # the same weights as the trained checkpoint, without its training state
    shipped_net, _ = load_model(shipped / "csg2d" / "model.pt")
    trained_net, _ = load_model(trained / "runs/pretrain/csg2d/best.pt")
    for (k, a), (_, b) in zip(shipped_net.state_dict().items(), trained_net.state_dict().items()):
        assert torch.equal(a, b), k
    assert model.checkpoint.stat().st_size <= (trained / "runs/pretrain/csg2d/best.pt").stat().st_size


def test_ships_at_once_write_whole_pairs_and_a_reader_never_takes_a_mixed_one(trained, shipped, tmp_path):
    import threading

    from plad.fsutil import file_lock
    from plad.shipped import LOCK, ShipError, ship, shipped_model

    dest = tmp_path / "shipped"
    shutil.copytree(shipped, dest)
    read = shipped_model("csg2d", dest)                # a command has read the sidecar, not yet the checkpoint
    metrics = tmp_path / "metrics.json"                # the same model's evaluation with another mean: a new sidecar
    record = json.loads((trained / "results/eval/sp/csg2d/metrics.json").read_text())
    record["test"]["mean"] = 1.25
    metrics.write_text(json.dumps(record))
    sidecar = dest / "csg2d" / "model.json"
    before = sidecar.read_bytes()
    done = []
    with file_lock(dest / "csg2d" / LOCK):          # another ship is writing the pair
        thread = threading.Thread(target=lambda: done.append(ship(
            "csg2d", trained / "runs/pretrain/csg2d/best.pt", metrics, dest=dest, root=trained,
            params=REPO / "params.yaml")))
        thread.start()
        thread.join(1.0)
        assert thread.is_alive() and sidecar.read_bytes() == before   # waits, writes nothing meanwhile
    thread.join(300)
    assert len(done) == 1 and done[0].test["mean"] == 1.25
    with pytest.raises(ShipError) as err:
        read.verify()
    assert str(err.value) == f"{sidecar}: the csg2d model was shipped again while this command read it; run the " \
                             "command again"
    now = shipped_model("csg2d", dest)
    now.verify()                                       # the new pair is whole
    assert now.test["mean"] == 1.25


def test_ship_refuses_metrics_of_another_model(trained, tmp_path, capsys):
    other = tmp_path / "other.json"
    record = json.loads((trained / "results/eval/sp/csg2d/metrics.json").read_text())
    other.write_text(json.dumps({**record, "checkpoint": "runs/finetune/csg2d/st/best.pt"}))
    status = main(["models", "ship", "csg2d", str(trained / "runs/pretrain/csg2d/best.pt"), "--metrics", str(other),
                   "--root", str(trained), "--params", str(REPO / "params.yaml"), "--dest", str(tmp_path / "s")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1 and len(err) == 1 and str(other) in err[0] and "not of" in err[0]   # ShipError: exit 1
    assert not (tmp_path / "s").exists()


def test_infer_uses_the_shipped_model_from_any_directory_and_creates_no_store(shipped, tmp_path):
    cwd = tmp_path / "anywhere"
    cwd.mkdir()
    assert main(["execute", "csg2d", PROGRAM, "-o", str(tmp_path / "shape.png")]) == 0
    res = cli("infer", "csg2d", str(tmp_path / "shape.png"), "--beam", "2", cwd=cwd,
              env={"PLAD_SHIPPED_DIR": str(shipped)})
    assert res.returncode == 0, res.stderr
    assert "model: shipped csg2d model (sp, test chamfer" in res.stderr and str(shipped) in res.stderr
    assert sorted(p.name for p in cwd.iterdir()) == ["inferred"]     # no mlflow.db, no mlruns/
    (run,) = (cwd / "inferred").iterdir()   # the run's own folder (plad.serve.infer.new_run_dir)
    assert (run / "shape.txt").read_text().strip().endswith("$")


def test_an_unconfigured_sqlite_store_is_not_created(shipped, tmp_path):
    db = tmp_path / "store" / "mlflow.db"
    res = cli("infer", "csg2d", str(REPO / "examples/csg2d"), "--beam", "1", "--out", str(tmp_path / "out"),
              cwd=tmp_path, env={"PLAD_SHIPPED_DIR": str(shipped), "MLFLOW_TRACKING_URI": f"sqlite:///{db}"})
    assert res.returncode == 0, res.stderr
    assert "model: shipped" in res.stderr and not db.exists() and not db.parent.exists()


def test_no_model_at_all_is_one_line(tmp_path):
    res = cli("infer", "csg2d", str(REPO / "examples/csg2d"), cwd=tmp_path,
              env={"PLAD_SHIPPED_DIR": str(tmp_path / "empty")})
    err = res.stderr.strip().splitlines()
    # no model is a failure of the run's data (exit status 1, plad.errors), found before any folder is made
    assert res.returncode == 1 and len(err) == 1 and "no csg2d model" in err[0] and "--model" in err[0]
    assert not (tmp_path / "mlflow.db").exists() and list(tmp_path.iterdir()) == []


def test_a_damaged_shipped_model_is_refused(shipped, tmp_path):
    copy = tmp_path / "shipped"
    shutil.copytree(shipped, copy)
    with open(copy / "csg2d" / "model.pt", "r+b") as fh:
        fh.seek(100)
        fh.write(b"\0" * 16)
    res = cli("infer", "csg2d", str(REPO / "examples/csg2d"), cwd=tmp_path, env={"PLAD_SHIPPED_DIR": str(copy)})
    err = res.stderr.strip().splitlines()
    assert res.returncode == 1 and len(err) == 1 and "differs from its sidecar" in err[0]


@pytest.fixture(scope="module")
def store(trained, tmp_path_factory):
    """A SQLite MLflow store whose plad-csg2d@champion is the trained tiny model (tagged with its test metric)."""
    import mlflow

    from plad import tracking
    from plad.tracking import StageRun

    root = tmp_path_factory.mktemp("store")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", uri)
    mlflow.set_tracking_uri(uri)
    with StageRun("report", "csg2d", {}, root / "run") as run:
        version = run.log_model(trained / "runs/pretrain/csg2d/best.pt",
                                registered_name="plad-csg2d").rsplit("/", 1)[1]
    tracking.set_champion("plad-csg2d", version)
    tracking.set_version_tags("plad-csg2d", version, {"plad.method": "sp", "plad.test": "7.5"})
    mp.undo()
    return root


def test_a_configured_store_with_a_champion_comes_first_and_models_lists_both(shipped, store, tmp_path):
    env = {"PLAD_SHIPPED_DIR": str(shipped), "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}"}
    res = cli("infer", "csg2d", str(REPO / "examples/csg2d"), "--beam", "1", cwd=tmp_path, env=env)
    assert res.returncode == 0, res.stderr
    assert "model: models:/plad-csg2d@champion" in res.stderr
    listed = cli("models", cwd=tmp_path, env=env)
    assert listed.returncode == 0, listed.stderr
    rows = [line.split() for line in listed.stdout.splitlines()[1:]]
    by_source = {r[1]: r for r in rows if r[0] == "csg2d"}
    assert set(by_source) == {"shipped", "registered"}
    assert by_source["shipped"][3:5] == ["chamfer", str(json.loads(
        (shipped / "csg2d/model.json").read_text())["metrics"]["mean"])]
    assert by_source["registered"][3] == "7.5" and by_source["registered"][4].startswith("*models:/plad-csg2d/")
    assert not by_source["shipped"][-1].startswith("*")
    # each model's provenance under its row: the shipped one's checkpoint, the registered one's run
    assert "provenance: from runs/pretrain/csg2d/best.pt" in listed.stdout
    assert "provenance: MLflow run " in listed.stdout
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "inferred") == []


def test_a_store_without_the_champion_falls_back_to_the_shipped_model(shipped, store, tmp_path, monkeypatch):
    from plad.serve.resolve import ModelError, resolve
    from plad.tracking.store import client

    shutil.copy(store / "mlflow.db", tmp_path / "mlflow.db")
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.setenv("PLAD_SHIPPED_DIR", str(shipped))
    monkeypatch.chdir(tmp_path)   # ./mlflow.db: the default store is configured
    assert resolve("csg2d").kind == "champion"
    with pytest.raises(ModelError, match="no csg3d model: no champion in the MLflow store"):
        resolve("csg3d")          # nothing registered, nothing shipped
    client().delete_registered_model_alias("plad-csg2d", "champion")
    choice = resolve("csg2d")
    assert choice.kind == "shipped" and "no champion in the MLflow store" in choice.notes[0]
    # a SQLite URI whose database is absent configures no store, and the look-up does not create it
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'elsewhere.db'}")
    assert resolve("csg2d").kind == "shipped" and not (tmp_path / "elsewhere.db").exists()
    # a configured store that cannot be opened: the shipped model, with the store's one-line error as the note
    broken = tmp_path / "broken" / "mlflow.db"
    broken.parent.mkdir()
    broken.write_text("not a database")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{broken}")
    choice = resolve("csg2d")
    assert choice.kind == "shipped" and choice.notes[0].startswith(
        f"no champion in the MLflow store (MLflow store sqlite:///{broken}: {broken} cannot be read as an SQLite "
        "database (file is not a database); move the file away")
    assert broken.read_text() == "not a database"


def test_the_pyfunc_loader_resolves_like_infer(shipped, monkeypatch):
    from plad.domains import get_domain
    from plad.serve.resolve import load_pyfunc

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.setenv("PLAD_SHIPPED_DIR", str(shipped))
    monkeypatch.chdir(shipped)   # no mlflow.db here: the shipped model
    domain = get_domain("csg2d")
    import torch

    shapes = domain.execute(torch.tensor([domain.parse(PROGRAM)])).numpy()
    out = load_pyfunc("csg2d").predict(shapes, params={"beam": 2})
    assert list(out.columns) == ["program", "chamfer", "error"] and len(out) == 1 and out["error"].isna().all()
    assert out["program"][0].endswith("$") and np.isfinite(out["chamfer"][0])
    assert sorted(p.name for p in shipped.iterdir()) == ["csg2d"]


def test_the_shipped_files_are_package_data():
    import fnmatch

    tomllib = pytest.importorskip("tomllib")
    from plad.shipped import CHECKPOINT, SIDECAR

    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    globs = config["package-data"]["plad.shipped"]
    for name in (CHECKPOINT, SIDECAR):
        assert any(fnmatch.fnmatch(f"csg2d/{name}", g) for g in globs), name
