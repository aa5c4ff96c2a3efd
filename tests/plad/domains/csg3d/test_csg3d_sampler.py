"""csg3d synthetic sampler: validity, the supplement's distributions and tree rule, non-degeneracy."""
import time

import numpy as np
import pytest

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.domains.csg3d.sampler import overlaps, random_tree, sample_primitives
from plad.domains.csg3d.tokens import program_tree
from tests.reference.csg3d_render import render_nodes

DOMAIN = get_domain("csg3d")


@pytest.fixture(scope="module")
def sampled():
    start = time.perf_counter()
    programs = DOMAIN.sample(10_000, np.random.default_rng(123))
    seconds = time.perf_counter() - start
    print(f"sampled 10000 csg3d programs in {seconds:.1f} s ({10_000 / seconds:.0f} programs/s)")
    return programs


def primitives_of(tree):
    if tree[0] in ("cuboid", "ellipsoid"):
        return [tree]
    return primitives_of(tree[1]) + primitives_of(tree[2])


def test_10000_programs_are_valid_and_follow_the_supplement(sampled):
    assert len(sampled) == 10_000
    ks = []
    kinds = {"cuboid": 0, "ellipsoid": 0}
    for ids in sampled:
        DOMAIN.check(ids)
        assert len(ids) <= 100
        prims = primitives_of(program_tree(ids))
        ks.append(len(prims))
        for kind, (x, y, z, dx, dy, dz) in prims:
            kinds[kind] += 1
            for c, d in ((x, dx), (y, dy), (z, dz)):
                m = min(c, 32 - c)
                assert 2 <= c <= 30 and 2 <= d <= 2 * m - 2, (c, d)
    counts = np.bincount(ks, minlength=13)
    assert counts[:2].sum() == 0 and counts[2:].sum() == 10_000
    # uniform over K = 2..12: 909 each, binomial sd about 29
    assert (np.abs(counts[2:] - 10_000 / 11) < 150).all(), counts
    share = kinds["ellipsoid"] / (kinds["cuboid"] + kinds["ellipsoid"])
    assert 0.45 < share < 0.55


def test_10000_programs_respect_the_overlap_rule_of_their_operators(sampled):
    seen = set()
    for ids in sampled:
        def visit(node):
            if node[0] in ("cuboid", "ellipsoid"):
                return [node[1]]
            a, b = visit(node[1]), visit(node[2])
            seen.add(node[0])
            if node[0] in ("diff", "inter"):
                ov = overlaps(np.array(b + a))[: len(b), len(b):]          # (|B|, |A|)
                assert ov.any(1).all(), "difference: every primitive of B must overlap one of A"
                if node[0] == "inter":
                    assert ov.any(0).all(), "intersection: every primitive of A must overlap one of B"
            return a + b
        visit(program_tree(ids))
    assert seen == {"union", "inter", "diff"}


def test_10000_programs_are_non_degenerate(sampled):
    # by the executor's per-operator check (the executor itself is tested equal to the reference)
    words, degenerate = DOMAIN.executor.run_packed(pad_programs(sampled), check_degenerate=True)
    assert not degenerate.any()
    assert (words != 0).any(dim=(1, 2)).all()


def test_operator_results_differ_from_both_operands_by_the_reference(sampled):
    # independently, with the numpy reference, on a subset (the reference is slow)
    for ids in sampled[:1000]:
        for op, out, a, b in render_nodes(DOMAIN.format(ids)):
            assert out.any() and not np.array_equal(out, a) and not np.array_equal(out, b), op


def test_primitive_distributions():
    params, ell = sample_primitives(20_000, np.random.default_rng(0))
    c, d = params[:, :3], params[:, 3:]
    assert c.min() >= 2 and c.max() <= 30
    m = np.minimum(c, 32 - c)
    assert (d >= 2).all() and (d <= 2 * m - 2).all()
    # center: a normal (16, 16/3) truncated to [2, 30] has mean 16 and sd a bit below 16/3
    assert abs(c.mean() - 16) < 0.1 and 4.8 < c.std() < 5.33
    assert 0.48 < ell.mean() < 0.52


def test_union_is_the_only_choice_for_disjoint_primitives():
    params = np.array([[5, 5, 5, 4, 4, 4], [25, 25, 25, 4, 4, 4], [5, 25, 5, 4, 4, 4]])
    rng = np.random.default_rng(0)
    for _ in range(50):
        names = random_tree(params, np.array([False, True, False]), rng)
        assert [w for w in names if w in ("union", "inter", "diff")] == ["union", "union"]


def test_sampling_is_deterministic_per_seed():
    a = DOMAIN.sample(50, np.random.default_rng(9))
    b = DOMAIN.sample(50, np.random.default_rng(9))
    assert a == b


# -- the "parts" sampler (beyond the paper) ----------------------------------------------------------------
@pytest.fixture(scope="module")
def parts():
    return DOMAIN.samplers()["parts"](600, np.random.default_rng(7))


def test_parts_programs_are_valid_non_degenerate_and_uniform_over_primitives(parts):
    assert len(parts) == 600
    ks = []
    for ids in parts:
        DOMAIN.check(ids)
        ks.append(len(primitives_of(program_tree(ids))))
    counts = np.bincount(ks, minlength=13)
    assert counts[:2].sum() == 0 and (counts[2:] > 600 / 11 * 0.6).all()   # every k of 2..12, none missing
    _, degenerate = DOMAIN.executor.run_packed(pad_programs(parts), check_degenerate=True)
    assert not degenerate.any()


def test_parts_are_unions_of_thin_mostly_mirrored_cuboids(parts):
    ops = {"union": 0, "diff": 0, "inter": 0}
    prims = thin = 0
    for ids in parts:
        for name in DOMAIN.format(ids).split():
            if name in ops:
                ops[name] += 1
        for _kind, (*_centre, dx, dy, dz) in primitives_of(program_tree(ids)):
            prims += 1
            thin += min(dx, dy, dz) <= 3
    assert ops["inter"] == 0 and ops["union"] > 3 * ops["diff"] > 0
    assert thin / prims > 0.6       # plates and sticks: 75% of the parts before the degeneracy filter
    shapes = DOMAIN.execute(__import__("torch").as_tensor(pad_programs(parts[:200])).long()).numpy()
    mirror = [(s & s[::-1]).sum() / (s | s[::-1]).sum() for s in shapes]
    assert np.mean(mirror) > 0.55   # the paper's sampler: about 0.3


def test_parts_sampler_is_seeded():
    sample = DOMAIN.samplers()["parts"]
    rng = np.random.default_rng
    assert sample(30, rng(1)) == sample(30, rng(1)) != sample(30, rng(2))


def test_an_unknown_sampler_is_a_config_error_naming_the_choices(tmp_path):
    from plad.config import ConfigError
    from plad.layout import Layout
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    with pytest.raises(ConfigError, match=r"sampler 'nope'.*'paper', 'parts'"):
        synthesize(SynthesizeConfig(domain="csg3d", sampler="nope", train_programs=2, val_programs=2), Layout(tmp_path))
