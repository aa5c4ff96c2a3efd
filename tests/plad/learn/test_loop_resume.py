"""A resumed run says so: the one loop (plad.learn.loop, every trainer's epochs and PLAD rounds) prints
"resuming from <unit> N" when it continues from a saved state, and nothing of the kind on a fresh start."""
from __future__ import annotations

import pytest

from plad.learn.loop import JsonStore, Limits, Loop, Objective, Unit

LOSS = Objective("loss", higher_is_better=False)


@pytest.mark.parametrize("unit_name", ["epoch", "round"])
def test_a_resumed_loop_prints_where_it_continues(unit_name, tmp_path, capsys):
    values = [5.0, 4.0, 4.5, 3.0]

    def step(unit, remaining):
        return Unit(values[unit - 1])

    first = Loop(unit_name, LOSS, Limits(max_units=2), JsonStore(tmp_path / "state.json")).run(step)
    assert first.units == 2
    assert "resuming" not in capsys.readouterr().err
    Loop(unit_name, LOSS, Limits(max_units=4), JsonStore(tmp_path / "state.json")).run(step)
    err = capsys.readouterr().err
    assert f"resuming from {unit_name} 3 (2 finished" in err
    assert f"best 4 at {unit_name} 2" in err
