"""Beam search over partial programs (plad.rewrite.beam) and the effort levels of a search."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plad.config import ConfigError
from plad.domains import domain_names, get_domain
from plad.domains.base import pad_programs
from plad.rewrite import EFFORTS, RefineConfig, search, search_config
from plad.rewrite.beam import beam_search
from plad.rewrite.evaluate import Scorer


def _execute(domain, programs):
    return domain.execute(pad_programs(programs))


def _targets(domain, n: int, seed: int) -> torch.Tensor:
    """Executions of sampled programs, half of them with a square carved out (off the sampler's family)."""
    rng = np.random.default_rng(seed)
    targets = _execute(domain, domain.sample(n, rng))
    hole = _execute(domain, [domain.parse("s(32,32,12)$")])[0]
    targets[::2] &= ~hole
    return targets


def test_beam_finds_are_distinct_sorted_and_exact():
    domain = get_domain("csg2d")
    targets = _targets(domain, 6, 0)
    scorer = Scorer(domain, targets)
    finds = beam_search(scorer, width=3, steps=3, finals=4)
    assert len(finds) == len(targets)
    for i, found in enumerate(finds):
        assert 1 <= len(found) <= 4
        programs = [p for p, _ in found]
        values = torch.tensor([v for _, v in found], dtype=torch.float64)
        for p in programs:
            domain.check(p)
            assert len(p) <= 6                                 # at most 3 primitives: d d op d op $
        # each value is the domain's own executor and metric; best first; distinct executions
        assert torch.equal(domain.metric(_execute(domain, programs), targets[i:i + 1].expand(len(programs), -1, -1)),
                           values)
        assert values.tolist() == sorted(values.tolist())
        outs = _execute(domain, programs).reshape(len(programs), -1)
        assert len({bytes(o.numpy()) for o in outs}) == len(programs)
    with pytest.raises(ValueError, match="at least 1"):
        beam_search(scorer, width=0, steps=3)


def test_beam_finds_do_not_depend_on_how_many_programs_are_extended_at_once(monkeypatch):
    import plad.rewrite.beam as beam

    domain = get_domain("csg2d")
    targets = _targets(domain, 4, 3)
    together = beam_search(Scorer(domain, targets), width=2, steps=2, finals=2)
    monkeypatch.setattr(beam, "PROGRAMS_PER_CALL", 1)
    assert beam_search(Scorer(domain, targets), width=2, steps=2, finals=2) == together


def test_beam_rebuilds_an_intersection_that_greedy_insertion_cannot():
    """Greedy insertion offers union and difference; the beam's children use every operator."""
    domain = get_domain("csg2d")
    target = _execute(domain, [domain.parse("s(32,32,24)t(32,40,28)*$")])
    beam = search(domain, target, search_config(domain, beam_width=4, insertions=2, **{"refine.rounds": 0}))
    assert float(beam.values[0]) == 0.0
    greedy = search(domain, target, search_config(domain, beam_width=0, insertions=2, **{"refine.rounds": 0}))
    assert float(greedy.values[0]) > 0.0


def test_beam_search_is_never_worse_than_its_start_and_reports_exact_values():
    """The start of a search is the empty program; the beam's first step already holds the best single
    primitive, so nothing it returns is worse than the one-primitive floor; and refinement keeps it so."""
    domain = get_domain("csg2d")
    targets = _targets(domain, 8, 1)
    floor = Scorer(domain, targets).values(domain.floor(targets.numpy()))
    for refine_rounds, beam_refine in ((0, 1), (1, 2)):
        cfg = search_config(domain, beam_width=2, insertions=3, beam_refine=beam_refine,
                            **{"refine.rounds": refine_rounds, "refine.po_sweeps": 1})
        result = search(domain, targets, cfg)
        assert bool((result.values <= floor).all())
        assert torch.equal(domain.metric(_execute(domain, result.programs), targets), result.values)
        if refine_rounds == 0:
            unrefined = result.values
    # refining the beam's finds never makes the answer worse than the beam's best find
    assert bool((result.values <= unrefined).all())


@pytest.mark.parametrize("name", ["csg2d", "csg3d"])
def test_greedy_first_keeps_per_shape_the_better_of_the_greedy_and_the_beam_search(name):
    """``greedy_first``: the greedy search runs, then the beam's refined finds replace its program only where
    better, so each shape gets exactly the better of the two searches run alone."""
    domain = get_domain(name)
    rng = np.random.default_rng(4)
    targets = _execute(domain, domain.sample(6, rng))
    common = dict(insertions=3, beam_refine=2, **{"refine.rounds": 1, "refine.po_sweeps": 1})
    greedy = search(domain, targets, search_config(domain, beam_width=0, **common))
    beam = search(domain, targets, search_config(domain, beam_width=2, **common))
    both = search(domain, targets, search_config(domain, beam_width=2, greedy_first=True, **common))
    pick = torch.maximum if domain.metric.higher_is_better else torch.minimum
    assert torch.equal(both.values, pick(greedy.values, beam.values))
    assert torch.equal(domain.metric(_execute(domain, both.programs), targets), both.values)
    assert both.stats.screened + both.stats.scored > beam.stats.screened + beam.stats.scored


def test_bad_beam_settings_are_one_line():
    domain = get_domain("csg2d")
    for key, value in (("beam_width", -1), ("beam_refine", 0)):
        with pytest.raises(ConfigError, match=f"{key} = {value}: expected") as err:
            search_config(domain, **{key: value})
        assert len(str(err.value).splitlines()) == 1
    with pytest.raises(ConfigError, match="greedy_first = true needs a beam") as err:
        search_config(domain, greedy_first=True, beam_width=0)
    assert len(str(err.value).splitlines()) == 1


def test_effort_levels_are_monotone_in_work():
    domain = get_domain("csg2d")
    targets = _targets(domain, 2, 2)
    work, values = [], []
    for effort in EFFORTS:      # three primitives at most, two PO sweeps: a tiny case
        result = search(domain, targets, search_config(domain, effort=effort, insertions=3, **{"refine.po_sweeps": 2}))
        work.append(result.stats.screened + result.stats.scored)
        values.append(float(result.values.mean()))
        assert torch.equal(domain.metric(_execute(domain, result.programs), targets), result.values)
    assert work[0] < work[1] < work[2], work
    assert search_config(domain, effort="fast").beam_width == 0      # fast: the greedy search
    # settings given beside the effort override the level's
    assert search_config(domain, effort="best", beam_width=3).beam_width == 3


@pytest.mark.parametrize("name", domain_names())
def test_every_domain_declares_every_effort(name):
    space = get_domain(name).rewrite
    assert set(space.search_efforts) == set(EFFORTS)
    configs = [search_config(get_domain(name), effort=e) for e in EFFORTS]
    assert [c.effort for c in configs] == list(EFFORTS)
    RefineConfig(**space.refine_defaults)     # the refinement of a network's programs: known fields only


def test_bad_effort_is_one_line():
    domain = get_domain("csg2d")
    for bad in ("quick", 3):
        with pytest.raises(ConfigError) as err:
            search_config(domain, effort=bad)
        assert len(str(err.value).splitlines()) == 1
        assert "effort" in str(err.value) and "fast, default, best" in str(err.value)


def test_csg3d_best_is_never_worse_than_default_per_shape():
    """3D CSG's ``best`` runs the ``default`` search with more refinement, then a beam that replaces a program
    only where better: per shape it can only gain."""
    domain = get_domain("csg3d")
    targets = _execute(domain, domain.sample(3, np.random.default_rng(7)))
    default = search(domain, targets, search_config(domain, effort="default", insertions=4))
    best = search(domain, targets, search_config(domain, effort="best", insertions=4))
    assert search_config(domain, effort="best").greedy_first
    assert bool((best.values >= default.values).all())
    assert torch.equal(domain.metric(_execute(domain, best.programs), targets), best.values)


def test_csg3d_seed_is_the_cuboid_around_the_shape():
    domain = get_domain("csg3d")
    targets = _execute(domain, domain.sample(4, np.random.default_rng(3)))
    targets = torch.cat([targets, torch.zeros(1, *domain.shape, dtype=torch.bool)])
    seeds = domain.rewrite.seeds(targets)
    assert seeds[-1] == []                                      # an empty shape has no seed
    for seed, target in zip(seeds[:-1], targets[:-1]):
        assert domain.format(seed).startswith("cuboid ") and len(seed) == 7
        box = _execute(domain, [seed])[0]
        assert bool((box | ~target).all())                      # covers the shape
        for axis in range(3):                                   # and its extent, give or take one voxel
            dims = tuple(a for a in range(3) if a != axis)
            t, b = torch.nonzero(target.any(dim=dims)).flatten(), torch.nonzero(box.any(dim=dims)).flatten()
            assert 0 <= t[0] - b[0] <= 1 and 0 <= b[-1] - t[-1] <= 1


def test_seeded_search_carves_the_seed():
    """Four table legs without a top, three insertions, no refinement: from the empty program the greedy
    search places three legs (0.75); from the seed, differences carve the legs out of their box (exact)."""
    domain = get_domain("csg3d")
    target = torch.zeros(1, *domain.shape, dtype=torch.bool)
    for x in (8, 22):
        for z in (8, 22):
            target[0, x:x + 3, 4:21, z:z + 3] = True
    common = dict(insertions=3, **{"refine.rounds": 0})
    plain = search(domain, target, search_config(domain, **common))
    seeded = search(domain, target, search_config(domain, seeded=True, **common))
    assert float(plain.values[0]) == 0.75
    assert float(seeded.values[0]) == 1.0
    assert domain.format(seeded.programs[0]).split()[:3] == ["diff", "diff", "diff"]


@pytest.mark.parametrize("name", ["csg2d", "csg3d"])
def test_seeded_search_is_never_worse_per_shape(name):
    """``seeded`` adds a search from the domain's seeds that replaces a shape's program only where better;
    a domain without seeds (2D CSG) gives exactly the search without."""
    domain = get_domain(name)
    rng = np.random.default_rng(5)
    targets = _targets(domain, 6, 5) if name == "csg2d" else _execute(domain, domain.sample(6, rng))
    common = dict(insertions=3, **{"refine.rounds": 1, "refine.po_sweeps": 1})
    plain = search(domain, targets, search_config(domain, **common))
    seeded = search(domain, targets, search_config(domain, seeded=True, **common))
    assert torch.equal(domain.metric(_execute(domain, seeded.programs), targets), seeded.values)
    if domain.rewrite.seeds(targets) is None:
        assert seeded.programs == plain.programs
    else:
        assert bool((seeded.values >= plain.values).all())


def test_eliminate_brings_programs_back_within_the_cap():
    """A 3D CSG program of 14 cuboids (111 tokens, past the cap of 100) loses its cheapest primitives until it
    fits; the values it reports are the executor's."""
    from plad.rewrite.prune import eliminate

    domain = get_domain("csg3d")
    rng = np.random.default_rng(2)
    boxes = [" ".join(["cuboid"] + [str(v) for v in rng.integers(6, 26, 3)] + [str(v) for v in rng.integers(2, 9, 3)])
             for _ in range(14)]
    # token by token: parsing would refuse a program past the cap
    long = [domain.tokens.index(word) for word in ("union " * 13 + " ".join(boxes)).split()]
    assert len(long) == 111
    target = _execute(domain, domain.sample(1, rng))
    scorer = Scorer(domain, target)
    short, values = eliminate(scorer, [long], scorer.values([long]), max_len=100)
    assert len(short[0]) <= 100 and len(short[0]) == 95      # two primitives fewer: 12 cuboids
    domain.check(short[0])
    assert torch.equal(domain.metric(_execute(domain, short), target), values)


def test_overshoot_search_is_never_worse_per_shape_and_returns_valid_programs():
    domain = get_domain("csg3d")
    targets = _execute(domain, domain.sample(4, np.random.default_rng(8)))
    common = dict(insertions=3, tune_sweeps=2, **{"refine.rounds": 1, "refine.po_sweeps": 1})
    plain = search(domain, targets, search_config(domain, **common))
    over = search(domain, targets, search_config(domain, overshoot=16, **common))
    assert bool((over.values >= plain.values).all())
    for p in over.programs:
        domain.check(p)                                         # within the language's cap again
    assert torch.equal(domain.metric(_execute(domain, over.programs), targets), over.values)
    assert domain.rewrite.max_len == domain.tokens.max_len       # the cap is back after the search


def test_overshoot_beyond_what_a_domain_allows_is_one_line():
    for name in ("csg2d", "shapeassembly"):
        with pytest.raises(ConfigError, match="overshoot = 4: the .* domain runs programs of at most 0 tokens") as err:
            search_config(get_domain(name), overshoot=4)
        assert len(str(err.value).splitlines()) == 1
    space = get_domain("csg3d").rewrite
    with pytest.raises(ValueError, match="0 to 100"):
        with space.longer(101):
            pass
    with pytest.raises(RuntimeError):
        with space.longer(8):
            assert space.max_len == space.domain.tokens.max_len + 8
            raise RuntimeError("inside")
    assert space.max_len == space.domain.tokens.max_len
