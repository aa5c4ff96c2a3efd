"""evaluate_finetuned@<domain>: every method's model and the beam sweep in one process, the files of one
evaluate run per model."""
from __future__ import annotations

import json

import pytest

from plad.layout import BEST, GRID, METRICS, Layout, programs_csv
from plad.stages.evaluate import EvaluateConfig, evaluate
from plad.stages.evaluate_finetuned import main
from tests.tiny import csg2d_inputs, tiny_checkpoint

METHODS = ["a", "b"]


@pytest.fixture(scope="module")
def project(tmp_path_factory, datasets_dir):
    root = csg2d_inputs(tmp_path_factory.mktemp("grouped"), datasets_dir)
    layout = Layout(root)
    for seed, method in enumerate(METHODS, start=1):   # two different fine-tuned models
        tiny_checkpoint(layout.model("csg2d", method), "csg2d", seed=seed)
    params = root / "params.yaml"
    params.write_text(f"methods: {METHODS}\nbeams: [1, 3]\n"
                      "evaluate:\n  base: {beam: 2, batch_size: 8, limit: 6, grid_shapes: 2, device: cpu}\n"
                      "  csg2d: {}\n")
    return root, params


def test_one_run_writes_every_method_and_beam_as_separate_evaluations_would(project, tmp_path, capsys):
    root, params = project
    assert main(["--params", str(params), "--section", "evaluate.csg2d", "--root", str(root),
                 "--sweep-method", "b"]) == 0
    printed = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert set(printed) == {"a", "b", "b_beam1", "b_beam3"}
    alone = Layout(tmp_path)   # the same evaluations, one evaluate call per model, into another root
    for method in METHODS:
        tiny_checkpoint(alone.model("csg2d", method), "csg2d", seed=METHODS.index(method) + 1)
        (alone.prepared("csg2d")).parent.mkdir(parents=True, exist_ok=True)
    alone.prepared("csg2d").write_bytes(Layout(root).prepared("csg2d").read_bytes())
    base = dict(domain="csg2d", beam=2, batch_size=8, limit=6, grid_shapes=2, device="cpu")
    runs = {"a": EvaluateConfig(**base, method="a"), "b": EvaluateConfig(**base, method="b"),
            "b_beam1": EvaluateConfig(**base, method="b", sweep_beam=1),
            "b_beam3": EvaluateConfig(**base, method="b", sweep_beam=3)}
    for key, cfg in runs.items():
        evaluate(cfg, alone)
        grouped, single = Layout(root).eval_dir(key, "csg2d"), alone.eval_dir(key, "csg2d")
        assert (grouped / programs_csv("test")).read_text() == (single / programs_csv("test")).read_text()
        assert (grouped / GRID).read_bytes() == (single / GRID).read_bytes()
        got, want = json.loads((grouped / METRICS).read_text()), json.loads((single / METRICS).read_text())
        for k in ("method", "beam", "refine", "metric"):
            assert got[k] == want[k] == printed[key][k]
        assert got["test"]["mean"] == want["test"]["mean"] and got["test"]["n"] == 6
    assert printed["a"]["test"]["mean"] != printed["b"]["test"]["mean"]   # each method's own model
    assert printed["b_beam1"]["beam"] == 1 and printed["b"]["beam"] == 2


def test_a_sweep_method_outside_methods_is_a_one_line_error(project, capsys):
    root, params = project
    assert main(["--params", str(params), "--section", "evaluate.csg2d", "--root", str(root),
                 "--sweep-method", "c"]) == 1
    err = capsys.readouterr().err.strip()
    assert "--sweep-method c is not one of methods (a, b)" in err and len(err.splitlines()) == 1


def test_a_missing_model_is_a_one_line_error(project, tmp_path, capsys):
    root, params = project
    empty = tmp_path / "root"
    (empty / "data").mkdir(parents=True)
    assert main(["--params", str(params), "--section", "evaluate.csg2d", "--root", str(empty),
                 "--sweep-method", "b"]) == 1
    err = capsys.readouterr().err.strip()
    assert str(Layout(empty).model("csg2d", "a")) in err and len(err.splitlines()) == 1
    assert not (Layout(empty).finetune_dir("csg2d", "a") / BEST).exists()
