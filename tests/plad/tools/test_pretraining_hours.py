"""The hours-of-pretraining curve: cumulative epoch seconds against the history's metrics."""
from __future__ import annotations

import math

import pytest

from plad.tools.pretraining_hours import curve, main


def write(path, rows):
    path.write_text("epoch,val_loss,val_iou,real_val_iou,prefix_gap,epoch_seconds\n" +
                    "".join(f"{e},{1 / e},{v},{r},0.1,{s}\n" for e, v, r, s in rows))
    return path


def test_curve_sums_epoch_seconds_into_hours(tmp_path):
    c = curve(write(tmp_path / "h.csv", [(1, 0.1, 0.05, 1800), (2, 0.2, 0.1, 3600), (3, 0.3, "", 1800)]))
    assert c["hours"] == [0.5, 1.5, 2.0] and c["epoch"] == [1, 2, 3]
    assert c["real_val_iou"][:2] == [0.05, 0.1] and math.isnan(c["real_val_iou"][2])
    assert c["val_iou"] == [0.1, 0.2, 0.3]


def test_main_draws_the_png_and_prints_the_best_epoch(tmp_path, capsys):
    h = write(tmp_path / "h.csv", [(1, 0.1, 0.05, 1800), (2, 0.2, 0.12, 1800), (3, 0.3, 0.1, 1800)])
    assert main(["-o", str(tmp_path / "out.png"), f"run a={h}"]) == 0
    assert (tmp_path / "out.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out == "run a: 3 epochs, 1.50 h; best real_val_iou 0.1200 at epoch 2 (1.00 h)\n"


def test_a_file_that_is_no_history_is_one_line(tmp_path, capsys):
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    assert main(["-o", str(tmp_path / "o.png"), f"x={tmp_path / 'x.csv'}"]) == 1
    assert capsys.readouterr().err.strip().endswith("not a pretraining history (no epoch_seconds column)")
    with pytest.raises(ValueError, match="cannot read"):
        curve(tmp_path / "missing.csv")


def test_shapes_seen_spreads_each_segments_shapes_over_its_epochs(tmp_path, capsys):
    h = write(tmp_path / "h.csv", [(1, 0.1, 0.05, 1800), (2, 0.2, 0.1, 1800), (3, 0.3, 0.2, 10), (4, 0.4, 0.3, 10)])
    # a CPU segment of 2 epochs and 0.2 M shapes, then a GPU segment of 2 epochs and 3 M shapes
    (tmp_path / "provenance.json").write_text(
        '{"segments": [{"epochs": [1, 2], "shapes_seen": 200000}, {"epochs": [3, 4], "shapes_seen": 3000000}]}')
    c = curve(h)
    assert c["shapes"] == pytest.approx([0.1, 0.2, 1.7, 3.2])
    assert main(["-o", str(tmp_path / "out.png"), "--x", "shapes", f"r={h}"]) == 0
    assert (tmp_path / "out.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out == ("r: 4 epochs, 1.01 h, 3.20 M shapes; best real_val_iou 0.3000 at epoch 4 "
                                       "(1.01 h)\n")


def test_shapes_axis_without_provenance_is_one_line(tmp_path, capsys):
    h = write(tmp_path / "h.csv", [(1, 0.1, 0.05, 1800)])
    assert main(["-o", str(tmp_path / "out.png"), "--x", "shapes", f"r={h}"]) == 1
    assert "no provenance.json beside it" in capsys.readouterr().err
    assert not (tmp_path / "out.png").exists()


def test_the_best_epoch_of_a_lower_is_better_metric_is_its_lowest(tmp_path, capsys):
    h = tmp_path / "h.csv"
    h.write_text("epoch,val_chamfer,real_val_chamfer,epoch_seconds\n"
                 "1,9.0,8.5,1800\n2,2.0,3.1,1800\n3,1.5,,1800\n4,1.0,2.9,1800\n5,1.1,3.0,1800\n")
    assert main(["-o", str(tmp_path / "out.png"), "--metric", "real_val_chamfer", f"2D={h}"]) == 0
    assert capsys.readouterr().out == "2D: 5 epochs, 2.50 h; best real_val_chamfer 2.9000 at epoch 4 (2.00 h)\n"
