"""The effort curve (plad.tools.effort): search and network + refinement points of every level, and its picture."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from plad.data.files import write_prepared
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.rewrite import search, search_config
from plad.tools.effort import main, measure, plot
from tests.tiny import tiny_model


def _targets(n: int = 3) -> np.ndarray:
    domain = get_domain("csg2d")
    return domain.execute(pad_programs(domain.sample(n, np.random.default_rng(3)))).numpy()


def test_points_are_the_searches_and_refinements_of_each_level():
    targets = _targets()
    model = tiny_model("csg2d")
    points = measure("csg2d", targets, model, levels=["fast", "default"])
    assert [(p["kind"], p["config"]) for p in points] == [
        ("search", "fast"), ("search", "default"), ("network", "beam 1"), ("network", "beam 10"),
        ("network + refinement", "fast"), ("network + refinement", "default")]
    # a search point is that search's mean, exactly (seconds aside)
    domain = get_domain("csg2d")
    direct = search(domain, torch.from_numpy(targets), search_config(domain, effort="default"))
    assert points[1]["mean"] == round(float(direct.values.mean()), 6)
    # refinement never makes the network's beam-10 programs worse (Chamfer: lower is better)
    beam10 = points[3]["mean"]
    assert all(p["mean"] <= beam10 for p in points[4:])
    assert all(p["s_per_shape"] > 0 for p in points)


def test_measure_writes_its_json_and_plot_draws_it(tmp_path):
    prepared = tmp_path / "prepared"
    prepared.mkdir()
    targets = _targets(4)
    write_prepared("csg2d", (64, 64), {"train": targets[:1], "val": targets[:1], "test": targets},
                   prepared / "csg2d.npz", prepared / "csg2d.json")
    out = tmp_path / "csg2d.json"
    main(["measure", "csg2d", "--spaced", "2", "--prepared", str(prepared), "--no-network", "--out", str(out)])
    report = json.loads(out.read_text())
    assert report["shapes"] == 2 and report["metric"] == "chamfer" and report["model"] is None
    assert [p["config"] for p in report["points"]] == ["fast", "default", "best"]
    assert report["provenance"]["torch_threads"] == 1
    png = tmp_path / "effort.png"
    plot([out], png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_names_a_file_that_is_not_an_effort_file(tmp_path):
    from plad.errors import BadInput

    broken, other = tmp_path / "broken.json", tmp_path / "other.json"
    broken.write_text('{"domain": "csg2d"')
    other.write_text('{"domain": "csg2d"}')
    with pytest.raises(BadInput, match=r"broken\.json: not a readable effort file \(JSONDecodeError"):
        plot([broken], tmp_path / "x.png")
    with pytest.raises(BadInput, match=r"other\.json: not an effort file of `measure` \(missing metric, "):
        plot([other], tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()
