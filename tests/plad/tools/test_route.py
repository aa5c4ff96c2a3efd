"""Measuring plad infer's route per domain (plad.tools.route): the path with the better metric, a tie the faster."""
from __future__ import annotations

from plad.tools.route import choose

POINTS = [{"kind": "search", "config": "default", "mean": 0.88, "s_per_shape": 0.24},
          {"kind": "network", "config": "beam 10", "mean": 0.40, "s_per_shape": 0.05},
          {"kind": "network + refinement", "config": "default", "mean": 0.85, "s_per_shape": 0.77}]


def test_the_route_is_the_path_with_the_better_metric():
    assert choose(POINTS, "default", higher_is_better=True)["route"] == "search"
    assert choose(POINTS, "default", higher_is_better=False)["route"] == "network"   # Chamfer: lower is better
    tie = [dict(p, mean=0.5) for p in POINTS]
    assert choose(tie, "default", higher_is_better=True)["route"] == "search"         # a tie: the faster
    entry = choose(POINTS, "default", True)
    assert entry["network"] == {"mean": 0.85, "s_per_shape": 0.77} and entry["effort"] == "default"


def test_measure_without_the_prepared_validation_shapes_is_one_line(tmp_path, capsys):
    from plad.tools.route import main

    assert main(["measure", "csg2d", "--prepared", str(tmp_path)]) == 1
    want = f"{tmp_path / 'csg2d.npz'}: no such prepared dataset (run the prepare stage first)"
    assert capsys.readouterr().err.strip() == want
