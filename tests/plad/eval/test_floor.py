"""Floor baselines (Domain.floor): one primitive in 2D, one box in 3D; evaluated with SP and shown in the table."""
from __future__ import annotations

import json

import numpy as np
import torch

from plad.domains import domain_names, get_domain
from plad.domains.base import pad_programs
from plad.eval.floor import evaluate_floor
from plad.eval.report import MethodResult, table_markdown


def _execute(domain, texts: list[str]) -> np.ndarray:
    return domain.execute(pad_programs([domain.parse(t) for t in texts])).numpy()


def test_every_domain_offers_a_floor():
    assert {get_domain(n).floor_name for n in domain_names()} == {"one primitive", "one box"}


def test_csg2d_floor_is_the_best_single_draw_token_by_the_metric():
    domain = get_domain("csg2d")
    targets = domain.execute(pad_programs(domain.sample(8, np.random.default_rng(1)))).numpy()
    values, programs = evaluate_floor(domain, targets)
    assert all(len(p) == 2 for p in programs)   # <draw> $
    draws = [i for i, t in enumerate(domain.tokens.tokens) if t.kind == "draw"]
    every = domain.metric.score_candidates(domain.executor.bitmaps[draws][None].expand(len(targets), -1, -1, -1),
                                           torch.from_numpy(targets))          # (8, 424) brute force
    np.testing.assert_allclose(values, every.min(1).values.numpy(), rtol=0, atol=1e-9)


def test_csg3d_floor_is_the_tightest_box():
    domain = get_domain("csg3d")
    # two cuboids whose bounding box is [8, 22] x [8, 18] x [8, 18]: centre (15, 13, 13), extents (15, 11, 11)
    target = _execute(domain, ["union cuboid 10 10 10 5 5 5 cuboid 19 16 14 7 5 9"])
    values, programs = evaluate_floor(domain, target)
    assert domain.format(programs[0]) == "cuboid 15 13 13 15 11 11"
    assert values[0] == target.sum() / (15 * 11 * 11)
    # a target that is one cuboid is its own floor
    values, _ = evaluate_floor(domain, _execute(domain, ["cuboid 3 29 16 6 4 31", "cuboid 30 1 16 5 3 2"]))
    assert (values == 1.0).all()


def test_shapeassembly_floor_of_a_centred_box_is_that_box():
    from plad.domains.shapeassembly.floor import box_program

    domain = get_domain("shapeassembly")
    target = _execute(domain, [box_program(12, 20, 8), box_program(31, 9, 25)])
    values, programs = evaluate_floor(domain, target)
    assert (values == 1.0).all()
    assert all(domain.format(p).endswith("Attach bbox top fpos_5_5 fpos_5_5 END") for p in programs)


def test_floor_row_in_the_table():
    names = domain_names()
    results = {n: [MethodResult("sp", 0.5)] for n in names}
    floors = {n: 0.25 for n in names}
    text = table_markdown(results, ["sp"], {}, floors=floors)
    row = next(line for line in text.splitlines() if line.startswith("| Floor: "))
    assert "one primitive (2D CSG)" in row and "one box (3D CSG, ShapeAssembly)" in row
    assert row.count("25.0") == 2 and "0.250" in row
    assert "Floor" not in table_markdown(results, ["sp"], {})
    assert "Floor" not in table_markdown(results, ["sp"], {}, floors={n: None for n in names})


def test_evaluating_sp_writes_the_floor(tmp_path, datasets_dir):
    from plad.layout import FLOOR, METRICS, SP, Layout, programs_csv
    from plad.stages.evaluate import EvaluateConfig, evaluate
    from plad.stages.report import floor_from_files
    from tests.tiny import csg2d_inputs

    layout = Layout(csg2d_inputs(tmp_path, datasets_dir))
    report = evaluate(EvaluateConfig(domain="csg2d", method=SP, beam=1, limit=12, grid_shapes=2,
                                      batch_size=12), layout)
    floor = json.loads((layout.eval_dir(FLOOR, "csg2d") / METRICS).read_text())
    assert floor == report[FLOOR] and floor["floor"] == "one primitive" and floor["test"]["n"] == 12
    assert (layout.eval_dir(FLOOR, "csg2d") / programs_csv("test")).read_text().count("\n") == 13
    assert floor_from_files("csg2d", layout) == floor["test"]["mean"]
    # a fine-tuned model's evaluation does not redo the floor
    (layout.eval_dir(FLOOR, "csg2d") / METRICS).unlink()
    layout.model("csg2d", "lest_st").parent.mkdir(parents=True)
    layout.model("csg2d", "lest_st").write_bytes(layout.model("csg2d").read_bytes())
    evaluate(EvaluateConfig(domain="csg2d", method="lest_st", beam=1, limit=4, grid_shapes=2), layout)
    assert not (layout.eval_dir(FLOOR, "csg2d") / METRICS).exists()
