"""Canonical labels (Domain.canonical): exactly the same execution, one form per class, applied to the labels."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from plad.domains import domain_names, get_domain
from plad.domains.base import pad_programs
from plad.learn.pbest import PBest
from plad.metrics import IOU


def _same_execution(domain, programs: list[list[int]], chunk: int = 2000) -> None:
    """Every program and its canonical form execute to the same shape; the form is valid, no longer, and fixed."""
    canon = [domain.canonical(p) for p in programs]
    for p, c in zip(programs, canon):
        domain.check(c)
        assert len(c) == len(p)
    for start in range(0, len(programs), chunk):   # batched execution
        a = domain.execute(pad_programs(programs[start:start + chunk]))
        b = domain.execute(pad_programs(canon[start:start + chunk]))
        differ = np.nonzero((a != b).flatten(1).any(1).numpy())[0]
        assert not len(differ), f"{domain.name}: {domain.format(programs[start + differ[0]])} -> " \
                                f"{domain.format(canon[start + differ[0]])} executes differently"
    assert all(domain.canonical(c) == c for c in canon[:500]), "canonical form is not a fixed point"


@pytest.mark.parametrize("name", domain_names())
def test_canonical_form_of_sampled_programs_executes_the_same(name):
    domain = get_domain(name)
    _same_execution(domain, domain.sample(1000, np.random.default_rng(7)))


@pytest.mark.slow
@pytest.mark.parametrize("name", domain_names())
def test_canonical_form_of_10000_sampled_programs_executes_the_same(name, request):
    # about 30 s for csg3d and longer for shapeassembly (its sampler): select with -m slow
    if "slow" not in (request.config.getoption("markexpr") or ""):
        pytest.skip("10,000 programs per domain: select with -m slow")
    domain = get_domain(name)
    _same_execution(domain, domain.sample(10_000, np.random.default_rng(11)))


def _random_csg3d(rng: np.random.Generator, n: int) -> list[list[int]]:
    """Programs with uniformly random parameters 1..31 (clipped primitives included) and random trees."""
    domain = get_domain("csg3d")
    out = []
    for _ in range(n):
        def tree(k: int) -> list[str]:
            if k == 1:
                return [str(rng.choice(["cuboid", "ellipsoid"]))] + [str(v) for v in rng.integers(1, 32, 6)]
            left = int(rng.integers(1, k))
            return [str(rng.choice(["union", "inter", "diff"]))] + tree(left) + tree(k - left)
        out.append(domain.parse(" ".join(tree(int(rng.integers(1, 7))))))
    return out


def test_csg3d_canonical_form_of_random_clipped_programs_executes_the_same():
    _same_execution(get_domain("csg3d"), _random_csg3d(np.random.default_rng(3), 3000))


def test_csg3d_every_cuboid_axis_and_every_ellipsoid_extent_keeps_its_voxels():
    domain = get_domain("csg3d")
    rng = np.random.default_rng(5)
    # every (centre, extent) of one axis, the other axes random
    cuboids = [domain.parse(f"cuboid {c} {rng.integers(1, 32)} {rng.integers(1, 32)} {d} "
                            f"{rng.integers(1, 32)} {rng.integers(1, 32)}") for c in range(1, 32) for d in range(1, 32)]
    # every extent triple of an ellipsoid, at a random centre (clipped near the borders)
    ellipsoids = [domain.parse("ellipsoid " + " ".join(str(v) for v in [*rng.integers(1, 32, 3), *d]))
                  for d in itertools.product(range(1, 32), repeat=3)]
    _same_execution(domain, cuboids + ellipsoids, chunk=4096)


def test_csg3d_cuboid_extents_2k_and_2k_plus_1_are_one_label():
    domain = get_domain("csg3d")
    for k in range(1, 8):
        a = domain.canonical(domain.parse(f"cuboid 16 16 16 {2 * k} {2 * k} {2 * k}"))
        b = domain.canonical(domain.parse(f"cuboid 16 16 16 {2 * k + 1} {2 * k + 1} {2 * k + 1}"))
        assert a == b and domain.format(a) == f"cuboid 16 16 16 {2 * k + 1} {2 * k + 1} {2 * k + 1}"
    # near a border, centre and extent that clip to the same voxels are one label too: [0, 5] in x
    a = domain.canonical(domain.parse("cuboid 1 16 16 9 3 3"))
    b = domain.canonical(domain.parse("cuboid 2 16 16 6 3 3"))
    assert a == b


def test_commutative_operands_are_ordered_and_difference_is_not():
    d3 = get_domain("csg3d")
    a, b = "cuboid 10 10 10 5 5 5", "ellipsoid 20 20 20 7 9 11"
    for op in ("union", "inter"):
        assert d3.canonical(d3.parse(f"{op} {a} {b}")) == d3.canonical(d3.parse(f"{op} {b} {a}"))
    assert d3.canonical(d3.parse(f"diff {a} {b}")) != d3.canonical(d3.parse(f"diff {b} {a}"))
    d2 = get_domain("csg2d")
    x, y = "c(32,32,16)", "s(24,40,12)"
    for op in "+*":
        assert d2.canonical(d2.parse(f"{x}{y}{op}$")) == d2.canonical(d2.parse(f"{y}{x}{op}$"))
    assert d2.canonical(d2.parse(f"{x}{y}-$")) != d2.canonical(d2.parse(f"{y}{x}-$"))


def test_csg2d_draw_tokens_need_no_snapping():
    """The reason the 2D hook only orders operands: no two draw tokens draw the same bitmap."""
    domain = get_domain("csg2d")
    draws = [i for i, t in enumerate(domain.tokens.tokens) if t.kind == "draw"]
    bitmaps = domain.executor.bitmaps[draws].flatten(1)
    assert len(torch.unique(bitmaps, dim=0)) == len(draws)


def test_pbest_stores_the_canonical_form():
    domain = get_domain("csg3d")
    program = domain.parse("union ellipsoid 20 20 20 7 9 11 cuboid 10 10 10 4 4 4")
    shape = domain.execute(torch.tensor([program])).numpy()
    pbest = PBest(1, domain.shape, domain.tokens.max_len, IOU, canonical=domain.canonical)
    pbest.update(np.array([0]), [program], np.array([1.0]), shape)
    assert pbest.program(0) == domain.canonical(program) != program
    assert (domain.execute(torch.tensor([pbest.program(0)])).numpy() == pbest.executions[:1]).all()


def test_synthesize_writes_canonical_labels(tmp_path):
    from plad.layout import Layout
    from plad.stages.synthesize import SynthesizeConfig, from_array, synthesize

    layout = Layout(tmp_path)
    synthesize(SynthesizeConfig(domain="csg3d", train_programs=60, val_programs=20), layout)
    domain = get_domain("csg3d")
    with np.load(layout.synthetic("csg3d")) as z:
        programs = from_array(z["train"]) + from_array(z["val"])
    assert len(programs) == 80
    assert all(domain.canonical(p) == p for p in programs)
