"""The whole pipeline with the smoke profile, run as the README says, in a temporary copy of the project.

The copy is a git repository of the project's files as they are in the working tree; the smoke profile
runs there with ``dvc exp run --temp -S profile=smoke`` (the README's command), which must leave every
committed file (the ``cpu`` results, ``dvc.lock``, ``params.yaml``) as it was. The experiment is then
applied to the copy's workspace so that the tests below can read its outputs.
"""
import csv
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from plad.tracking.rows import display_name
from tests.conftest import REPO_ROOT

pytestmark = [pytest.mark.skipif(shutil.which("dvc") is None, reason="dvc is not installed"), pytest.mark.pipeline,
              pytest.mark.slow_first]


def run(cmd, cwd, env):
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    assert res.returncode == 0, f"{' '.join(cmd)} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    return res


def project_files() -> list[str]:
    """The repository's files: committed or new, not ignored, present in the working tree."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO_ROOT,
                         capture_output=True, text=True, check=True).stdout
    return sorted(f for f in set(out.split("\0")) if f and (REPO_ROOT / f).is_file())


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory, datasets_dir):
    work = tmp_path_factory.mktemp("pipeline")
    for name in project_files():
        (work / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO_ROOT / name, work / name)
    env = {**os.environ, "PLAD_DATA_DIR": str(datasets_dir), "DVC_NO_ANALYTICS": "1",
           "MLFLOW_TRACKING_URI": f"sqlite:///{work / 'mlflow.db'}", "GIT_AUTHOR_NAME": "t",
           "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    env.pop("PLAD_PIPELINE_ID", None)
    run(["git", "init", "-q"], work, env)
    run(["git", "add", "-A"], work, env)
    run(["git", "commit", "-q", "-m", "the project"], work, env)
    res = run(["dvc", "exp", "run", "--temp", "-S", "profile=smoke", "-n", "smoke"], work, env)
    status = run(["git", "status", "--porcelain"], work, env).stdout
    run(["dvc", "exp", "apply", "smoke"], work, env)
    return work, env, res, status


def test_smoke_profile_leaves_the_committed_files_alone(smoke_run):
    *_, status = smoke_run
    assert status == ""


def test_smoke_repro_writes_metrics_and_grid(smoke_run):
    work, *_ = smoke_run
    metrics = json.loads((work / "results" / "eval" / "sp" / "csg2d" / "metrics.json").read_text())
    assert metrics["method"] == "sp" and metrics["metric"] == "chamfer" and metrics["beam"] == 10
    assert metrics["test"]["n"] == 20 and 0 <= metrics["test"]["mean"] <= 16
    grid = work / "results" / "eval" / "sp" / "csg2d" / "grid.png"
    assert grid.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = (work / "results" / "eval" / "sp" / "csg2d" / "test_programs.csv").read_text().splitlines()
    assert len(lines) == 21 and lines[0] == "index,chamfer,program"
    summary = json.loads((work / "runs" / "pretrain" / "csg2d" / "summary.json").read_text())
    assert summary["units"] == 2 and summary["unit_name"] == "epoch"
    for domain in ("csg3d", "shapeassembly"):
        sp = json.loads((work / "results" / "eval" / "sp" / domain / "metrics.json").read_text())
        assert sp["metric"] == "iou" and sp["higher_is_better"] and sp["test"]["n"] == 10
        assert 0 <= sp["test"]["mean"] <= 1
    built = json.loads((work / "data" / "prepared" / "partnet_voxels.json").read_text())
    assert built["listed"] == {"train": 20, "val": 20, "test": 20} and built["failures"] == []


def test_smoke_repro_is_tracked_in_mlflow(smoke_run):
    work, env, *_ = smoke_run
    import mlflow

    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    # the pipeline's runs in plad, each domain's in plad-<domain>
    runs = mlflow.search_runs(experiment_names=["plad", *(f"plad-{d}" for d in DOMAINS)])
    stages = set(runs["tags.plad.stage"])
    assert {"pretrain", "evaluate", "finetune", "report"} <= stages
    assert (runs["status"] == "FINISHED").all()
    assert runs["tags.plad.pipeline"].nunique() == 1  # one repro, one group
    # one MLflow run per evaluation, also where one stage process evaluates every model (evaluate_finetuned@<d>)
    evaluated = runs[runs["tags.plad.stage"] == "evaluate"]
    for domain in DOMAINS:
        keys = set(evaluated[evaluated["tags.plad.domain"] == domain]["tags.plad.method"])
        assert keys == {"sp", *METHODS, "lest_st_per_round", "lest_st_ws_search", "lest_st_ws_search_refined",
                        *(f"lest_st_ws_search_beam{b}" for b in (1, 5, 10)), "taught", "taught_refined",
                        *(f"lest_st_ws_search_refined_{e}" for e in ("fast", "default", "best"))}
    finetuned = runs[(runs["tags.plad.stage"] == "finetune") & runs["tags.plad.round"].isna()]
    for domain in DOMAINS:
        mine = finetuned[finetuned["tags.plad.domain"] == domain]
        assert set(mine["tags.plad.method"]) == set(METHODS) | {"lest_st_per_round", "lest_st_ws_search"}
    finetuned = finetuned[finetuned["tags.plad.domain"] == "csg2d"]
    rounds = runs[runs["tags.mlflow.parentRunId"].isin(finetuned["run_id"])]
    ws = finetuned[finetuned["tags.plad.method"] == "lest_st_ws"].iloc[0]
    ws_rounds = rounds[rounds["tags.mlflow.parentRunId"] == ws["run_id"]]
    assert sorted(ws_rounds["tags.plad.round"]) == ["1", "2"]       # one nested run per round
    assert ws_rounds["metrics.pbest_mean"].notna().all() and ws_rounds["metrics.pbest_improved"].notna().all()
    pre = runs[(runs["tags.plad.stage"] == "pretrain") & (runs["tags.plad.domain"] == "csg2d")].iloc[0]
    assert pre["params.train.batch_size"] == "32"
    client = mlflow.tracking.MlflowClient()
    history = client.get_metric_history(pre["run_id"], "val_loss")
    assert len(history) == 2  # one value per epoch
    assert [a.path for a in client.list_artifacts(pre["run_id"], "checkpoint")] == ["checkpoint/best.pt"]
    model = mlflow.pyfunc.load_model(f"runs:/{pre['run_id']}/model")  # the logged model loads and infers
    out = model.predict(np.zeros((2, 64, 64), dtype=bool) | (np.arange(64) > 31)[None, None, :])
    assert len(out) == 2 and "program" in out.columns


def test_smoke_repro_top_level_is_the_results_table(smoke_run):
    """MLflow's top level: in each domain's experiment (plad-<domain>) one row run per result key named with its
    test value, in plad the pipeline's; every stage run nested under its row (plad.tracking.rows)."""
    work, env, *_ = smoke_run
    import mlflow

    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    client = mlflow.MlflowClient()
    names = ["plad", *(f"plad-{d}" for d in DOMAINS)]
    experiments = {name: client.get_experiment_by_name(name) for name in names}
    assert all(e.tags["mlflow.experimentKind"] == "custom_model_development" for e in experiments.values())
    runs = mlflow.search_runs(experiment_names=names)
    top = runs[runs["tags.mlflow.parentRunId"].isna()]
    assert set(top["tags.plad.row"]) == {"result", "pipeline"}          # no stage run at the top level
    # every run of a domain in its experiment, the pipeline's (the report) in plad
    stage_domain = runs["tags.plad.domain"].where(runs["tags.plad.stage"] != "report")
    expected = stage_domain.map(lambda d: experiments["plad" if not isinstance(d, str) else f"plad-{d}"].experiment_id)
    assert (runs["experiment_id"] == expected).all()
    rows = top[top["tags.plad.row"] == "result"]
    keys = {"sp", "floor", "search", *METHODS, "lest_st_per_round", "lest_st_ws_search", "lest_st_ws_search_refined",
            *(f"lest_st_ws_search_beam{b}" for b in (1, 5, 10)), "taught", "taught_refined",
            # the effort stages' rows (search_effort@<d>, evaluate_effort@<d>)
            "search_fast", "search_best", *(f"lest_st_ws_search_refined_{e}" for e in ("fast", "default", "best"))}
    for domain in DOMAINS:
        mine = rows[rows["tags.plad.domain"] == domain]
        assert sorted(mine["tags.plad.method"]) == sorted(keys)          # one row each
        for _, row in mine.iterrows():
            key = row["tags.plad.method"]
            test = json.loads((work / "results" / "eval" / key / domain / "metrics.json").read_text())["test"]["mean"]
            metric = "chamfer" if domain == "csg2d" else "iou"
            assert row["metrics.test_metric"] == pytest.approx(test, abs=1e-6)
            assert row["tags.mlflow.runName"] == f"{display_name(key)} · {test:.4g}"
            assert row["tags.plad.metric"] == metric
        for key in METHODS:   # fine-tuned: validation value, training time and stop reason under the same names
            row = mine[mine["tags.plad.method"] == key].iloc[0]
            assert row["metrics.val_metric"] > 0 and row["metrics.train_seconds"] > 0
            assert row["tags.plad.stopped"] in ("max_rounds", "max_epochs", "budget", "patience")
            assert row["metrics.seconds_per_shape"] > 0
    by_id = top.set_index("run_id")
    stages = runs[runs["tags.plad.stage"].notna() & runs["tags.plad.round"].isna()]
    for _, run in stages.iterrows():
        parent = by_id.loc[run["tags.mlflow.parentRunId"]]
        if run["tags.plad.stage"] == "report":
            assert parent["tags.plad.row"] == "pipeline"
        else:
            assert (parent["tags.plad.domain"], parent["tags.plad.method"]) == \
                (run["tags.plad.domain"], run["tags.plad.method"] if run["tags.plad.stage"] != "pretrain" else "sp")
    pipeline = top[top["tags.plad.row"] == "pipeline"].iloc[0]
    assert pipeline["tags.mlflow.runName"] == "pipeline · smoke"
    artifacts = {a.path for a in client.list_artifacts(pipeline["run_id"])}
    assert {"table.md", "convergence.png", "amortization.png"} <= artifacts


#: the slice of the pipeline run again (dvc.yaml's commands): 2D CSG from its synthetic programs to two
#: fine-tunings, the search-seeded one (search workers, rewriting, wake-sleep) and RL
SLICE = [["synthesize", "--section", "synthesize.csg2d"], ["pretrain", "--section", "pretrain.csg2d"],
         ["evaluate", "--section", "evaluate.csg2d"],
         ["finetune", "--section", "finetune.csg2d", "--set", "key=lest_st_ws_search"],
         ["finetune", "--section", "finetune.csg2d", "--set", "key=rl"]]
#: what the slice writes
SLICE_OUTPUTS = ["data/synthetic/csg2d.npz", "data/synthetic/csg2d.json", "runs/pretrain/csg2d",
                 "results/eval/sp/csg2d", "results/eval/floor/csg2d", "runs/finetune/csg2d/lest_st_ws_search",
                 "runs/finetune/csg2d/rl", "results/finetune/csg2d/lest_st_ws_search.json",
                 "results/finetune/csg2d/rl.json"]


def same_content(a, b, where: str) -> None:
    """``a`` and ``b`` (a file's decoded content) hold the same values, wall-clock measurements aside: dicts
    without :func:`plad.provenance.is_timing` keys, tensors and arrays exactly equal."""
    import torch

    from plad.provenance import is_timing

    if isinstance(a, dict):
        assert isinstance(b, dict), where
        keys = [k for k in a if not is_timing(str(k))]
        assert keys == [k for k in b if not is_timing(str(k))], where
        for k in keys:
            same_content(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            same_content(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b), where
    else:
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"   # NaN == NaN here


def same_file(a, b, name: str) -> None:
    """Two runs' versions of one output are the same: byte for byte, except the wall-clock measurements a
    file holds (metrics and state JSON, the loop state and provenance in checkpoints, a search chunk's seconds, the
    pretraining history's epoch seconds)."""
    import torch

    if a.suffix == ".json":
        same_content(json.loads(a.read_text()), json.loads(b.read_text()), name)
        pa, pb = (json.loads(f.read_text()).get("provenance") for f in (a, b))
        if pa is not None:   # the same settings, by the hash of the stage's resolved params
            assert pb is not None and pa["params_hash"] == pb["params_hash"], name
    elif a.suffix == ".pt":   # every checkpoint carries its pretraining's provenance, training seconds included
        same_content(torch.load(a, weights_only=True), torch.load(b, weights_only=True), name)
    elif a.suffix == ".npz" and a.parent.parent.name == "search":
        with np.load(a) as za, np.load(b) as zb:
            same_content({k: za[k] for k in za.files}, {k: zb[k] for k in zb.files}, name)
    elif a.name == "history.csv":
        rows = [[{k: v for k, v in r.items() if k != "epoch_seconds"} for r in csv.DictReader(f.open())]
                for f in (a, b)]
        assert rows[0] == rows[1], name
    else:
        assert a.read_bytes() == b.read_bytes(), name


def test_a_stage_run_again_gives_the_same_numbers_and_checkpoints(smoke_run, tmp_path):
    """Budgets in work, one torch thread: the slice's stages run again (one process each, a root of their own)
    give every metrics file, checkpoint and state file of the pipeline's run, wall-clock measurements aside."""
    work, env, *_ = smoke_run
    again = tmp_path / "again"
    for name in ["params.yaml", "profiles", "data/prepared/csg2d.npz", "data/prepared/csg2d.json"]:
        (again / name).parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if (work / name).is_dir() else shutil.copy2)(work / name, again / name)
    # the copy's code; an MLflow store of its own (the tests above count the pipeline's runs)
    env = {**env, "PYTHONPATH": str(work), "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    for stage, *args in SLICE:
        run([sys.executable, "-m", f"plad.stages.{stage}", "--params", "params.yaml", *args], again, env)
    compared = 0
    for output in SLICE_OUTPUTS:
        first = work / output
        files = sorted(p for p in first.rglob("*") if p.is_file()) if first.is_dir() else [first]
        assert files, output
        for path in files:
            if path.name in ("mlflow_run.json", ".gitignore"):   # the run's id in its MLflow store; DVC's file
                continue
            rel = path.relative_to(work)
            assert (again / rel).is_file(), f"{rel}: not written again"
            same_file(path, again / rel, str(rel))
            compared += 1
    assert compared >= 30   # every checkpoint, state and metrics file of the slice (P_BEST, search chunks, ...)
    summary = json.loads((again / "results" / "finetune" / "csg2d" / "lest_st_ws_search.json").read_text())
    assert summary["stopped"] == "max_rounds" and summary["stopped_by_time"] is False


def test_smoke_repro_is_up_to_date_afterwards(smoke_run):
    work, env, *_ = smoke_run
    res = run(["dvc", "status"], work, env)
    assert "changed" not in res.stdout


METHODS = ["rl", "ws", "st", "lest", "lest_st", "lest_st_ws"]
DOMAINS = ["csg2d", "csg3d", "shapeassembly"]


def test_smoke_repro_writes_the_whole_table(smoke_run):
    work, *_ = smoke_run
    table = (work / "results" / "table.md").read_text()
    main = table.split("## Fine-tuning runs")[0]
    rows = [line.split("|")[1].strip() for line in main.splitlines() if line.startswith("| ") and "---" not in line]
    assert rows == ["method", "SP", "RL", "WS", "ST", "LEST", "LEST+ST", "LEST+ST+WS",
                    "Floor: one primitive (2D CSG), one box (3D CSG, ShapeAssembly)"]
    floor_row = next(line for line in main.splitlines() if line.startswith("| Floor"))
    assert "—" not in floor_row.split("|")[2] + floor_row.split("|")[4] + floor_row.split("|")[6]   # measured
    assert "2D CSG: chamfer" in main and "3D CSG: iou x100" in main and "ShapeAssembly: iou x100" in main
    assert "| LEST+ST | " in table.split("all-time vs per-round")[1]
    lines = {line.split("|")[1].strip(): line for line in main.splitlines() if line.startswith("| ")}
    for domain, n, scale, digits in [("csg2d", 20, 1, 3), ("csg3d", 10, 100, 1), ("shapeassembly", 10, 100, 1)]:
        for key in ["sp", *METHODS, "lest_st_per_round"]:
            m = json.loads((work / "results" / "eval" / key / domain / "metrics.json").read_text())
            assert m["method"] == key and m["test"]["n"] == n
            if key != "lest_st_per_round":
                label = {"sp": "SP", "rl": "RL", "ws": "WS", "st": "ST", "lest": "LEST", "lest_st": "LEST+ST",
                         "lest_st_ws": "LEST+ST+WS"}[key]
                assert f"| {m['test']['mean'] * scale:.{digits}f} |" in lines[label]
        for key in METHODS:
            state = json.loads((work / "runs" / "finetune" / domain / key / "state.json").read_text())
            assert len(state["history"]) == 3  # start + 2 rounds (RL: 2 epochs)
    assert (work / "results" / "convergence.png").read_bytes()[:4] == b"\x89PNG"


def test_report_rebuilds_from_mlflow_alone(smoke_run, tmp_path):
    work, env, *_ = smoke_run
    out = tmp_path / "from_mlflow"   # a root without any of the pipeline's files
    run(["python", "-m", "plad.stages.report", "--params", "params.yaml", "--set", "source=mlflow",
         "--set", "register=false", "--root", str(out)], work, env)
    # the paper's table comes from MLflow alone; the rows beyond the paper are read from the evaluation
    # files whatever the source (plad/stages/report.py), and this root has none, so they are not compared
    beyond = "## Beyond the paper"
    assert (out / "results" / "table.md").read_text().split(beyond)[0] == \
        (work / "results" / "table.md").read_text().split(beyond)[0]


def test_report_registers_the_champion(smoke_run):
    """The smoke profile evaluates a few test shapes: its champions live under plad-<domain>-smoke (issue 54),
    never as plad-<domain>@champion, which `plad infer` would take."""
    work, env, *_ = smoke_run
    import mlflow

    mlflow.set_tracking_uri(env["MLFLOW_TRACKING_URI"])
    client = mlflow.MlflowClient()
    report = json.loads((work / "results" / "report.json").read_text())
    for domain in DOMAINS:
        champ = report["domains"][domain]["champion"]
        version = client.get_model_version_by_alias(f"plad-{domain}-smoke", "champion")
        assert str(version.version) == champ["version"] and version.tags["plad.method"] == champ["method"]
        assert version.tags["plad.profile"] == "smoke" and version.tags["plad.test_set"] == "subset"
    assert not [m.name for m in client.search_registered_models() if m.name in {f"plad-{d}" for d in DOMAINS}]


def test_smoke_repro_writes_the_rows_beyond_the_paper(smoke_run):
    work, *_ = smoke_run
    ev = work / "results" / "eval"
    for domain, n, higher in [("csg2d", 20, False), ("csg3d", 10, True), ("shapeassembly", 10, True)]:
        search = json.loads((ev / "search" / domain / "metrics.json").read_text())
        assert search["test"]["n"] == n and search["test"]["seconds_per_shape"] > 0
        refined = json.loads((ev / "lest_st_ws_search_refined" / domain / "metrics.json").read_text())["test"]
        beam10 = json.loads((ev / "lest_st_ws_search_beam10" / domain / "metrics.json").read_text())["test"]
        assert refined["network_mean"] == beam10["mean"]        # the same model, beam and shapes
        assert (refined["mean"] >= refined["network_mean"]) if higher else (refined["mean"] <= refined["network_mean"])
        for beam in (1, 5):
            assert json.loads((ev / f"lest_st_ws_search_beam{beam}" / domain / "metrics.json").read_text())["beam"] \
                == beam
        state = json.loads((work / "runs" / "finetune" / domain / "lest_st_ws_search" / "state.json").read_text())
        assert state["history"][1]["seed_shapes"] > 0 and state["history"][1]["rewrite_shapes"] > 0
    assert "Not computed" not in (work / "results" / "amortization.md").read_text()
    table = (work / "results" / "table.md").read_text()
    assert "| search, no network |" in table and "Not computed" not in table
    assert (work / "results" / "amortization.png").read_bytes()[:4] == b"\x89PNG"


def test_smoke_repro_labels_the_training_shapes_and_teaches_a_network(smoke_run):
    """Beyond the paper (issue 58): search labels of the first 12 training shapes of the labelling order, a
    network taught by them from where params.yaml starts it (the shipped SP or the search-seeded network), and its
    test evaluation alone and refined."""
    import yaml

    work, *_ = smoke_run
    teach = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())["teach"]
    smoke = yaml.safe_load((REPO_ROOT / "profiles" / "smoke.yaml").read_text())["teach"]
    for domain in DOMAINS:
        init = (teach.get(domain) or {}).get("init", teach["base"]["init"])
        labels = json.loads((work / "data" / "labels" / f"{domain}.json").read_text())
        assert labels["n"] == 12 and labels["rescored_max_difference"] == 0.0 and labels["chunks"] == 2
        taught = json.loads((work / "results" / "finetune" / domain / "taught.json").read_text())
        # a second segment where params.yaml asks for one (teach.<domain>.then), of the smoke profile's epochs
        then = (teach.get(domain) or {}).get("then")
        more = (smoke.get(domain) or {})["then"]["max_epochs"] if then else 0
        assert taught["key"] == "taught" and taught["units"] == 2 + more and taught["labels"] == 12
        assert taught["init"] == init and taught["stopped"] == "max_epochs"
        if then:
            assert taught["first"]["units"] == 2 and taught["then"]["grow"] == then["grow"]
            assert (work / "runs" / "finetune" / domain / "taught" / "first" / "best.pt").is_file()
        for key in ("taught", "taught_refined"):
            metrics = json.loads((work / "results" / "eval" / key / domain / "metrics.json").read_text())
            assert metrics["method"] == "taught" and metrics["test"]["n"] > 0
