"""plad infer's route per domain (plad.serve.route): the recorded route for its network, and search when chosen."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from plad.serve.route import read_routes, route_for

#: a route as plad.tools.route records it: search measured better
ENTRY = {"route": "search", "effort": "default", "network": {"mean": 0.85, "s_per_shape": 0.77},
         "search": {"mean": 0.88, "s_per_shape": 0.24}}


def test_a_route_applies_only_to_the_network_it_was_measured_with(tmp_path):
    entry = {**ENTRY, "shapes": 50, "model_sha256": "abc"}
    (tmp_path / "routes.json").write_text(json.dumps({"format": 1, "domains": {"shapeassembly": entry}}))
    route, why = route_for("shapeassembly", "abc", tmp_path)
    assert route == "search" and "50 validation shapes" in why and "0.8800" in why
    assert route_for("shapeassembly", "other", tmp_path)[0] == "network"
    assert route_for("csg3d", "abc", tmp_path) == ("network", "no route measured for this domain")
    (tmp_path / "routes.json").write_text("{not json")
    assert read_routes(tmp_path) == {}


def test_infer_takes_the_search_route(tmp_path, monkeypatch):
    """--route search: programs from search from scratch, as good as the search finds, in the same outputs."""
    from plad.serve.cli import main

    repo = __import__("tests.conftest", fromlist=["REPO_ROOT"]).REPO_ROOT
    image = repo / "examples" / "csg2d" / "gear.png"
    if not image.exists():
        pytest.skip("no example image")
    shutil.copy(image, tmp_path / "gear.png")
    monkeypatch.chdir(tmp_path)
    code = main(["infer", "csg2d", "gear.png", "--route", "search", "--effort", "fast", "--out", "out"])
    assert code == 0
    rows = list((tmp_path / "out").glob("*/results.csv"))
    assert len(rows) == 1
    lines = rows[0].read_text().splitlines()
    assert lines[0].startswith("file,index,name,status,chamfer") and ",ok," in lines[1]
    value = float(lines[1].split(",")[4])
    assert np.isfinite(value) and value < 3.0
