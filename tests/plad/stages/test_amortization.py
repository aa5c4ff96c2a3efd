"""Test-time refinement, the beam sweep, search-only rows and the report beyond the paper (amortization)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from plad.config import ConfigError
from plad.layout import AMORTIZATION_PLOT, AMORTIZATION_TABLE, METRICS, SEARCH, SP, TABLE, Layout, programs_csv
from plad.stages.evaluate import EvaluateConfig, evaluate
from plad.stages.report import AmortizationConfig, ReportConfig, report


def _values(path: Path) -> np.ndarray:
    with path.open() as fh:
        return np.array([float(r["chamfer"]) for r in csv.DictReader(fh)])


@pytest.fixture(scope="module")
def root(csg2d_project):
    return csg2d_project


def test_evaluate_with_refinement_is_never_worse_on_the_same_shapes(root):
    layout = Layout(root)
    base = dict(domain="csg2d", beam=2, batch_size=8, limit=8, grid_shapes=2, device="cpu")
    plain = evaluate(EvaluateConfig(**base), layout)
    refined = evaluate(EvaluateConfig(**base, refine=True, refine_config={"rounds": 1, "po_sweeps": 2}), layout)
    before = _values(layout.eval_dir(SP, "csg2d") / programs_csv("test"))
    after = _values(layout.eval_dir("sp_refined", "csg2d") / programs_csv("test"))
    assert len(before) == len(after) == 8
    assert (after <= before).all() and after.mean() < before.mean()   # Chamfer: lower is better
    t = refined["test"]
    assert t["network_mean"] == plain["test"]["mean"] and t["mean"] == pytest.approx(after.mean(), abs=1e-6)
    assert t["refine_seconds_per_shape"] > 0 and t["network_seconds_per_shape"] > 0
    assert t["seconds_per_shape"] == pytest.approx(t["network_seconds_per_shape"] + t["refine_seconds_per_shape"])
    assert plain["test"]["refine_seconds_per_shape"] < 1e-3 and not plain["refine"] and refined["refine"]
    with pytest.raises(ConfigError, match="refine_config"):
        evaluate(EvaluateConfig(**base, refine=True, refine_config={"roundz": 1}), layout)


def test_a_beam_of_the_sweep_has_its_own_result_folder(root):
    layout = Layout(root)
    got = evaluate(EvaluateConfig(domain="csg2d", beam=10, sweep_beam=1, limit=4, grid_shapes=2, device="cpu"),
                   layout)
    saved = json.loads((layout.eval_dir("sp_beam1", "csg2d") / METRICS).read_text())
    assert got["beam"] == saved["beam"] == 1 and saved["test"]["n"] == 4


def _indices(path: Path) -> list[int]:
    with path.open() as fh:
        return [int(r["index"]) for r in csv.DictReader(fh)]


def test_a_limit_takes_shapes_evenly_spaced_over_the_split(root):
    """PartNet's splits are ordered by category: a limit must not mean the first shapes (chairs only). The
    programs file names each shape's index in the split, and its value is the one the full split gives."""
    from plad.data.files import load_prepared
    from plad.stages.search_only import SearchOnlyConfig, search_only

    layout = Layout(root)
    n = len(load_prepared(layout.prepared("csg2d"), "test"))
    want = np.linspace(0, n - 1, 4).round().astype(int).tolist()
    assert want[-1] == n - 1 and n > 4
    evaluate(EvaluateConfig(domain="csg2d", beam=1, limit=4, grid_shapes=2, device="cpu"), layout)
    csv_path = layout.eval_dir(SP, "csg2d") / programs_csv("test")
    assert _indices(csv_path) == want
    limited = _values(csv_path)
    evaluate(EvaluateConfig(domain="csg2d", beam=1, grid_shapes=2, device="cpu"), layout)
    assert _indices(csv_path) == list(range(n))
    assert _values(csv_path)[want] == pytest.approx(limited, abs=1e-6)
    search_only(SearchOnlyConfig(domain="csg2d", limit=3, search={"insertions": 1, "refine": {"rounds": 0}}),
                layout)
    assert _indices(layout.eval_dir(SEARCH, "csg2d") / programs_csv("test")) == \
        np.linspace(0, n - 1, 3).round().astype(int).tolist()


def test_search_only_writes_the_row_with_seconds_per_shape(root):
    from plad.stages.search_only import SearchOnlyConfig, search_only

    layout = Layout(root)
    got = search_only(SearchOnlyConfig(domain="csg2d", limit=3, search={"insertions": 2, "refine": {"rounds": 0}}),
                      layout)
    saved = json.loads((layout.eval_dir(SEARCH, "csg2d") / METRICS).read_text())
    assert saved["test"]["n"] == 3 and saved["test"]["seconds_per_shape"] > 0
    assert _values(layout.eval_dir(SEARCH, "csg2d") / programs_csv("test")).mean() == \
        pytest.approx(got["test"]["mean"], abs=1e-6)
    with pytest.raises(ConfigError, match="search"):
        search_only(SearchOnlyConfig(domain="csg2d", limit=1, search={"insertionz": 2}), layout)
    with pytest.raises(ConfigError, match="effort = 'quick': expected one of fast, default, best") as err:
        search_only(SearchOnlyConfig(domain="csg2d", limit=1, search={"effort": "quick"}), layout)
    assert len(str(err.value).splitlines()) == 1


def _metrics(layout: Layout, key: str, domain: str, mean: float, seconds: float, n: int = 10, **extra) -> None:
    path = layout.eval_dir(key, domain) / METRICS
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"test": {"mean": mean, "n": n, "seconds": seconds * n,
                                         "seconds_per_shape": seconds, **extra}}))


def test_the_report_builds_with_and_without_the_rows_beyond_the_paper(tmp_path):
    layout = Layout(tmp_path)
    _metrics(layout, SP, "csg2d", 1.5, 0.01)
    cfg = ReportConfig(domains=["csg2d"], methods=["sp"], per_round={},
                       beyond=[SEARCH, "lest_st_ws_search", "lest_st_ws_search_refined"],
                       amortization=AmortizationConfig("lest_st_ws_search"), beams=[1, 5, 10])
    report(cfg, layout)   # none of the new inputs exists: still a report, naming what is missing
    table = (layout.results_dir / TABLE).read_text()
    assert "| SP | 1.50" in table and "Beyond the paper" in table
    assert "Not computed (no metrics.json): csg2d/search, csg2d/lest_st_ws_search," in table
    amort = (layout.results_dir / AMORTIZATION_TABLE).read_text()
    assert "csg2d/lest_st_ws_search_beam1" in amort and (layout.results_dir / AMORTIZATION_PLOT).stat().st_size > 0

    _metrics(layout, SEARCH, "csg2d", 1.0, 0.2)
    _metrics(layout, "lest_st_ws_search", "csg2d", 1.2, 0.02)
    _metrics(layout, "lest_st_ws_search_refined", "csg2d", 0.9, 0.3, network_seconds_per_shape=0.02,
             refine_seconds_per_shape=0.28)
    for beam, (v, s) in {1: (1.4, 0.002), 5: (1.25, 0.01), 10: (1.2, 0.02)}.items():
        _metrics(layout, f"lest_st_ws_search_beam{beam}", "csg2d", v, s)
    summary = report(cfg, layout)
    table = (layout.results_dir / TABLE).read_text()
    assert "| search, no network | 1.000 | 200.0 ms |" in table
    assert "| LEST+ST+WS + search-seeded P_BEST + test-time refinement | 0.900 | 300.0 ms |" in table
    assert "Not computed" not in table
    amort = (layout.results_dir / AMORTIZATION_TABLE).read_text()
    assert "| LEST+ST+WS + search-seeded P_BEST, beam 1 (network) | 1.400 | 2.0 ms | 100.0 |" in amort
    assert "| 0.900 | 300.0 ms | 0.7 | 20.0 ms | 280.0 ms |" in amort and "Not computed" not in amort
    assert "| search, no network (search only) | 1.000 | 200.0 ms | 1.0 |" in amort
    assert summary["domains"]["csg2d"]["amortization"]["search"]["test"] == 1.0


def test_plad_infer_refine_is_never_worse_than_without(root, tmp_path, capsys):
    from plad.data.files import load_prepared
    from plad.serve.cli import main

    layout = Layout(root)
    shapes = load_prepared(layout.prepared("csg2d"), "test")[:3]
    for i, shape in enumerate(shapes):
        np.save(tmp_path / f"s{i}.npy", shape)
    got, runs = {}, {}
    for flag in (["--no-refine"], []):   # plad infer refines by default
        out = tmp_path / ("plain" if flag else "refined")
        assert main(["infer", "csg2d", *(str(tmp_path / f"s{i}.npy") for i in range(3)), "--model",
                     str(layout.model("csg2d")), "--beam", "2", "--out", str(out), *flag]) == 0
        (run,) = out.iterdir()   # each plad infer run writes into a folder of its own
        runs[not flag] = run
        with (run / "results.csv").open() as fh:
            got[not flag] = np.array([float(r["chamfer"]) for r in csv.DictReader(fh)])
    assert (got[True] <= got[False]).all() and got[True].mean() < got[False].mean()
    # what is written is the refined program: plad score of its files gives the reported value
    capsys.readouterr()
    assert main(["score", "csg2d", "--pred", str(runs[True] / "s0.recon.npy"),
                 "--target", str(runs[True] / "s0.input.npy")]) == 0
    assert float(capsys.readouterr().out.split()[-1]) == pytest.approx(got[True][0], abs=1e-5)


def test_search_at_an_effort_level_writes_its_own_row(root):
    from plad.stages.search_only import SearchOnlyConfig, search_only

    layout = Layout(root)
    search_only(SearchOnlyConfig(domain="csg2d", limit=3, search={"insertions": 1, "refine": {"rounds": 0}}), layout)
    default = (layout.eval_dir(SEARCH, "csg2d") / METRICS).read_text()
    got = search_only(SearchOnlyConfig(domain="csg2d", limit=3, search={"effort": "fast"}), layout)
    saved = json.loads((layout.eval_dir("search_fast", "csg2d") / METRICS).read_text())
    assert got["method"] == saved["method"] == "search_fast" and saved["config"]["effort"] == "fast"
    assert saved["test"]["n"] == 3 and saved["test"]["mean"] == got["test"]["mean"]
    assert (layout.eval_dir(SEARCH, "csg2d") / METRICS).read_text() == default   # the default row untouched
    with pytest.raises(ConfigError, match="search.effort = 'quick': expected one of fast, default, best"):
        SearchOnlyConfig(domain="csg2d", search={"effort": "quick"})


@pytest.mark.parametrize("effort", ["fast", "best"])
def test_evaluate_at_an_effort_level_gives_what_plad_infer_refines(root, effort):
    """The report's effort rows: the network's programs refined as ``plad infer --effort`` refines them (at
    ``best``, every candidate of the beam, the best kept), per shape exactly its values on the same batch."""
    import torch

    from plad.domains import get_domain
    from plad.eval.refinement import refinement
    from plad.model.checkpoint import load_model
    from plad.model.decode import infer_programs
    from plad.serve.infer import refine_inferred

    layout = Layout(root)
    base = dict(domain="csg2d", beam=3, batch_size=8, limit=4, grid_shapes=2, device="cpu")
    got = evaluate(EvaluateConfig(**base, refine_effort=effort), layout)
    out = layout.eval_dir(f"sp_refined_{effort}", "csg2d")
    saved = json.loads((out / METRICS).read_text())
    assert saved["refine_effort"] == effort and saved["refine"] and saved["refine_all_candidates"] == (effort == "best")
    values = _values(out / programs_csv("test"))
    assert got["test"]["mean"] == pytest.approx(values.mean(), abs=1e-6)
    assert (values <= _network_values(layout, base) + 1e-9).all()   # Chamfer: never worse than the beam's best
    assert got["test"]["refined_starts"] > 4 if effort == "best" else got["test"]["refined_starts"] == 4
    # a trial profile's overrides on top of the level: no rounds, so each shape keeps the best of its beam
    unrefined = evaluate(EvaluateConfig(**base, refine_effort=effort, effort_overrides={"rounds": 0}), layout)
    assert unrefined["test"]["mean"] == unrefined["test"]["network_mean"] == got["test"]["network_mean"]
    assert [c.refine_effort for c in EvaluateConfig(**base, effort_levels=["fast", "best"]).levels()] == \
        ["fast", "best"]

    from plad.data.files import load_split

    targets, _ = load_split(layout.prepared("csg2d"), "test", 4)
    model, _ = load_model(layout.model("csg2d", SP), torch.device("cpu"), expect_domain="csg2d")
    domain = get_domain("csg2d")
    shapes = torch.from_numpy(targets)
    _, want = refine_inferred(domain, infer_programs(model, domain, shapes, 3), shapes, refinement(domain, effort))
    assert values == pytest.approx(want.numpy(), abs=1e-6)
    with pytest.raises(ConfigError, match="refine_effort = 'quick': expected one of fast, default, best"):
        EvaluateConfig(**base, refine_effort="quick")


def _network_values(layout: Layout, base: dict) -> np.ndarray:
    evaluate(EvaluateConfig(**base), layout)
    return _values(layout.eval_dir(SP, "csg2d") / programs_csv("test"))


def test_the_report_carries_every_effort_level_and_tables_the_chosen_ones(tmp_path):
    from plad.stages.report import EffortsConfig

    layout = Layout(tmp_path)
    _metrics(layout, SP, "csg2d", 1.5, 0.01)
    for key, (v, s) in {"search_fast": (0.85, 0.13), SEARCH: (0.82, 0.3), "search_best": (0.78, 3.1),
                        "lest_st_ws_search_refined_fast": (0.9, 0.1), "lest_st_ws_search_refined_default": (0.86, 0.2),
                        "lest_st_ws_search_refined_best": (0.8, 1.8)}.items():
        _metrics(layout, key, "csg2d", v, s)
    cfg = ReportConfig(domains=["csg2d"], methods=["sp"], per_round={}, beyond=[SEARCH],
                       amortization=AmortizationConfig("lest_st_ws_search"), beams=[1],
                       efforts=EffortsConfig(levels=["fast", "default", "best"], table=["default", "best"]))
    summary = report(cfg, layout)
    efforts = summary["domains"]["csg2d"]["efforts"]
    assert list(efforts) == ["fast", "default", "best"]
    assert efforts["best"]["search"]["test"] == 0.78 and efforts["fast"]["network + refinement"]["test"] == 0.9
    assert efforts["default"]["search"]["seconds_per_shape"] == 0.3
    table = (layout.results_dir / TABLE).read_text()
    assert "| search, no network | 0.820 | 300.0 ms |" in table
    assert "| search, no network, effort best | 0.780 | 3.10 s |" in table
    assert "| LEST+ST+WS + search-seeded P_BEST + test-time refinement, effort default | 0.860 | 200.0 ms |" in table
    assert "effort fast" not in table   # fast is in the curve, not the table
    amort = (layout.results_dir / AMORTIZATION_TABLE).read_text()
    assert "| search, no network, effort fast (search only) | 0.850 | 130.0 ms | 2.3 |" in amort
    assert "| LEST+ST+WS + search-seeded P_BEST + test-time refinement, effort best (network + refinement) | 0.800 |" \
        in amort
    with pytest.raises(ValueError, match="every level of the table must be one of levels"):
        EffortsConfig(levels=["fast"], table=["best"])
    with pytest.raises(ValueError, match="'quick' is not an effort level"):
        EffortsConfig(levels=["quick"])


def test_the_layouts_effort_levels_are_the_searchs():
    from plad.layout import EFFORT_LEVELS, eval_key, search_key, split_effort
    from plad.rewrite import EFFORTS

    assert EFFORT_LEVELS == EFFORTS
    for level in EFFORTS:
        assert split_effort(search_key(level)) == (SEARCH, None if level == "default" else level)
        assert split_effort(eval_key("lest_st", effort=level)) == ("lest_st_refined", level)
    assert split_effort("lest_st_beam5") == ("lest_st_beam5", None) and split_effort("st_fast") == ("st_fast", None)
