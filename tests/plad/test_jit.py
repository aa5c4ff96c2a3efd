"""plad.jit: a process runs the tensor paths until it has given them about a second of work, then compiled."""
from __future__ import annotations

import subprocess
import sys

import pytest

from plad import jit


@pytest.fixture
def fresh():
    saved = jit._spent, jit._loaded
    jit.reset()
    yield
    jit._spent, jit._loaded = saved


def test_auto_mode_compiles_once_the_work_adds_up_to_the_load_cost(fresh):
    assert jit.installed()
    assert [jit.use(None, 0.4), jit.use(None, 0.4), jit.use(None, 0.3), jit.use(None, 0.0)] == [False, False, True,
                                                                                                True]
    jit.reset()
    assert jit.use(None, 2.0)                       # one call worth more than loading: compiled at once


def test_the_callers_switch_wins(fresh):
    assert jit.use(True, 0.0) and not jit._loaded   # forced, without counting as earned
    assert not jit.use(False, 5.0) and jit._spent == 0.0
    jit.load()
    assert jit.use(None, 0.0) and not jit.use(False, 0.0)


CHILD = """
import sys, numpy as np, torch, importlib
chamfer = importlib.import_module("plad.metrics.chamfer")
from plad.domains import get_domain
d = get_domain("csg3d")
d.execute(torch.tensor([d.parse("cuboid 16 16 16 8 8 8")] * 4))
x = torch.zeros({n}, 64, 64, dtype=torch.bool); x[:, 10:30, 5:40] = True
chamfer.chamfer(x, torch.roll(x, 2, 1))
print("numba" in sys.modules)
"""


@pytest.mark.parametrize("n, loaded", [(4, False), (12000, True)])
def test_a_short_process_never_imports_numba_a_long_one_does(n, loaded):
    out = subprocess.run([sys.executable, "-c", CHILD.format(n=n)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(loaded)
