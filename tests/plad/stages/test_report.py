"""The report's rows for MLflow's top level (``report.json``'s ``rows``): the numbers of every row of the tables."""
from __future__ import annotations

from plad.eval.report import MethodResult, Timed
from plad.stages.report import result_rows


def test_result_rows_take_each_number_from_where_the_table_does():
    results = [
        MethodResult("sp", 3.9),   # SP has no fine-tuning curve of its own
        MethodResult("st", 3.2, curve=[(0.0, 3.96), (10.0, 3.5)], train_seconds=10.0, val_best=3.5, rounds=2,
                     stopped="max_rounds"),
        MethodResult("ws", 3.1, curve=[(0.0, 3.96), (8.0, 3.4)], train_seconds=8.0, val_best=3.4, rounds=2,
                     stopped="budget"),
    ]
    timed = {"sp": Timed("sp", 3.9, 0.2), "st": Timed("st", 3.2, 0.05), "ws": None,
             "search": Timed("search", 2.8, 1.5), "st_beam1": Timed("st_beam1", 3.4, 0.01)}
    rows = result_rows(results, 3.5, timed, {"train_seconds": 600.0, "stopped": "patience"})
    assert rows == {
        # SP: the pretrained model's validation value is where every fine-tuning curve starts; its training is
        # pretraining's
        "sp": {"test": 3.9, "val": 3.96, "seconds_per_shape": 0.2, "train_seconds": 600.0, "stopped": "patience"},
        "st": {"test": 3.2, "val": 3.5, "seconds_per_shape": 0.05, "train_seconds": 10.0, "stopped": "max_rounds"},
        "ws": {"test": 3.1, "val": 3.4, "train_seconds": 8.0, "stopped": "budget"},   # no timing file: no time
        "search": {"test": 2.8, "seconds_per_shape": 1.5},
        "st_beam1": {"test": 3.4, "seconds_per_shape": 0.01},
        "floor": {"test": 3.5},
    }
    # a pretraining that continued another: SP's training is all of it
    continued = {"train_seconds": 60.0, "stopped": "patience", "totals": {"train_seconds": 3660.0, "segments": 2}}
    assert result_rows(results[:1], None, {}, continued)["sp"]["train_seconds"] == 3660.0
    # without fine-tuning runs, pretraining's summary or a floor: only what is known
    assert result_rows([MethodResult("sp", 3.9)], None, {}, {}) == {"sp": {"test": 3.9}}
