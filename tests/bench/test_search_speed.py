"""bench.search_speed: a search and a refinement find the same programs and values with every speedup off (the
baseline) and on, and the baseline's switches are put back after it."""
from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from bench import search_speed
from plad.domains import bits, get_domain
from plad.domains.base import pad_programs
from plad.rewrite import refine, search, search_config


@pytest.mark.parametrize("name", ["csg2d", "csg3d"])
def test_search_and_refinement_are_identical_with_the_speedups_off_and_on(name):
    domain = get_domain(name)
    programs = domain.sample(3, np.random.default_rng(5))
    targets = domain.execute(pad_programs(programs))
    torch.set_num_threads(1)
    cfg = search_config(domain, effort="fast")
    base, new, identical = search_speed.compare(functools.partial(search, domain, targets, cfg), repeats=1)
    assert identical and base > 0 and new > 0
    starts = [[t for t in p] for p in programs]
    refined = search_config(domain, **{"refine.rounds": 1}).refine
    assert search_speed.compare(functools.partial(refine, domain, starts, targets, refined), repeats=1)[2]
    assert bits._BITWISE_COUNT is not None       # the baseline's switch is put back


def test_the_baseline_runs_every_batch_through_the_batched_executors_and_puts_them_back():
    executors = [get_domain("csg2d").executor, get_domain("csg2d").rewrite._extended, get_domain("csg3d").executor]
    with search_speed._baseline():
        assert [e.per_program for e in executors] == [False] * 3 and bits._BITWISE_COUNT is None
    assert [e.per_program for e in executors] == [True] * 3
    from plad.domains import boxes
    from tests.reference import boxes_v0

    with search_speed._baseline():
        assert boxes.grow_box is boxes_v0.grow_box
    assert boxes.grow_box is not boxes_v0.grow_box
    import importlib

    chamfer = importlib.import_module("plad.metrics.chamfer")
    executor = importlib.import_module("plad.domains.csg3d.executor")
    voxels = importlib.import_module("plad.data.datasets.partnet.voxels")
    with search_speed._baseline():
        assert chamfer._COMPILED is False          # the 2D Chamfer on its tensor path
        assert executor._COMPILED is False         # 3D CSG's numpy path
        assert voxels._COMPILED is False           # ShapeAssembly's counts as matrix products
    # put back: the default rule (plad.jit)
    assert chamfer._COMPILED is None and executor._COMPILED is None and voxels._COMPILED is None


def test_a_changed_program_or_value_is_not_identical():
    class R:
        def __init__(self, programs, values):
            self.programs, self.values = programs, torch.tensor(values)

    assert search_speed._same(R([[1, 2]], [0.5]), R([[1, 2]], [0.5]))
    assert not search_speed._same(R([[1, 2]], [0.5]), R([[1, 3]], [0.5]))
    assert not search_speed._same(R([[1, 2]], [0.5]), R([[1, 2]], [0.25]))
