"""The fit of a taught network beside its validation against hours of teaching (plad.tools.teaching_fit)."""
from __future__ import annotations

import json


def test_the_teaching_plot_reads_histories_and_draws_one_panel_per_domain(tmp_path):
    from plad.learn.teach import _write_history
    from plad.tools.teaching_fit import curve, main

    run = tmp_path / "runs" / "finetune" / "csg3d" / "taught"
    run.mkdir(parents=True)
    _write_history(run / "history.csv", [
        {"unit": 0, "val": 0.3, "fit": 0.31, "fit_wide": 0.4, "unit_seconds": 36.0},
        {"unit": 1, "val": 0.4, "train_loss": 1.5, "fit": 0.5, "fit_wide": 0.6, "unit_seconds": 3600.0}])
    (run / "summary.json").write_text(json.dumps({"domain": "csg3d", "metric": "iou", "fit_labels_mean": 0.9}))
    c = curve(run / "history.csv")
    assert c["hours"] == [0.01, 1.01] and c["fit"] == [0.31, 0.5] and c["val"] == [0.3, 0.4]
    out = tmp_path / "fit.png"
    assert main([str(run / "history.csv"), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    assert main([str(tmp_path / "bad.csv"), "-o", str(tmp_path / "x.png")]) == 1


def test_the_teaching_plot_reads_the_committed_summaries_history(tmp_path):
    from plad.tools.teaching_fit import curve, main

    folder = tmp_path / "results" / "finetune" / "shapeassembly"
    folder.mkdir(parents=True)
    summary = {"domain": "shapeassembly", "metric": "iou", "fit_labels_mean": 0.8, "history": [
        {"val": 0.25, "train_loss": 2.0, "fit": 0.28, "fit_wide": 0.33, "seconds": 1800.0},
        {"val": 0.3, "train_loss": 1.9, "fit": 0.35, "seconds": 5400.0}]}
    (folder / "taught.json").write_text(json.dumps(summary))
    c = curve(folder / "taught.json")
    assert c["hours"] == [0.5, 1.5] and c["epoch"] == [1.0, 2.0] and c["val"] == [0.25, 0.3]
    assert c["fit_wide"][0] == 0.33 and c["fit_wide"][1] != c["fit_wide"][1]     # missing: NaN
    out = tmp_path / "fit.png"
    assert main([str(folder / "taught.json"), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "other.json").write_text(json.dumps({"domain": "csg2d"}))
    assert main([str(tmp_path / "other.json"), "-o", str(tmp_path / "x.png")]) == 1
    (tmp_path / "broken.json").write_text("{")
    assert main([str(tmp_path / "broken.json"), "-o", str(tmp_path / "y.png")]) == 1


def test_runs_of_one_domain_share_its_panel_named_by_their_growth(tmp_path):
    from plad.tools.teaching_fit import main, run_name

    paths = []
    for name, grow in (("plain", None), ("grown", {"enc_channels": [8, 16, 32, 64]})):
        summary = {"domain": "csg3d", "metric": "iou", "fit_labels_mean": 0.79, "history": [
            {"val": 0.5, "fit": 0.5, "fit_wide": 0.55, "seconds": 200.0},
            {"val": 0.55, "fit": 0.56, "fit_wide": 0.6, "seconds": 400.0}], **({"grow": grow} if grow else {})}
        path = tmp_path / name / "taught.json"
        path.parent.mkdir()
        path.write_text(json.dumps(summary))
        paths.append(str(path))
    assert run_name({}) == "the start's size"
    assert run_name({"grow": {"enc_channels": [8, 16, 32, 64], "n_layers": 4}}) == \
        "grown: enc_channels 8-16-32-64, n_layers 4"
    assert run_name({"grow": {"enc_channels": [8, 16, 32, 64]}, "then": {"grow": {"n_layers": 5, "dim_ff": 512}}}) \
        == "grown: enc_channels 8-16-32-64; then n_layers 5, dim_ff 512"
    for against in ("epoch", "hours"):
        out = tmp_path / f"{against}.png"
        assert main([*paths, "-o", str(out), "--against", against]) == 0
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_run_continuing_a_kept_network_is_drawn_after_the_run_before_it(tmp_path):
    from plad.tools.teaching_fit import continued, load_run, main, run_name

    def summary(name: str, init: str, seconds: list[float], grow: dict) -> object:
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"domain": "csg3d", "metric": "iou", "init": init, "grow": grow, "history": [
            {"val": 0.5 + i / 100, "fit": 0.6, "seconds": s} for i, s in enumerate(seconds)]}))
        return path

    first = summary("first", "search_seeded", [1800.0, 3600.0, 7200.0], {"enc_channels": [8, 16]})
    then = summary("then", "taught", [900.0, 1800.0], {"n_layers": 5})
    again = summary("again", "taught", [3600.0], {"dim_ff": 512})
    runs = continued([load_run(p) for p in (first, then, again)])
    assert runs[0][1]["hours"] == [0.5, 1.0, 2.0] and runs[0][1]["epoch"] == [1.0, 2.0, 3.0]
    assert runs[1][1]["hours"] == [2.25, 2.5] and runs[1][1]["epoch"] == [4.0, 5.0]
    assert runs[2][1]["hours"] == [3.5] and runs[2][1]["epoch"] == [6.0]            # a chain adds up
    assert run_name(runs[1][2]) == "continued, grown: n_layers 5"
    # alone (the run before it not listed) it starts at its own zero
    assert continued([load_run(then)])[0][1]["hours"] == [0.25, 0.5]
    assert main([str(first), str(then), "-o", str(tmp_path / "fit.png")]) == 0
