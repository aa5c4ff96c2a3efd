"""Program rewriting and search (plad.rewrite): properties on every domain, seeded."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plad.domains import domain_names, get_domain
from plad.domains.base import pad_programs
from plad.rewrite import RefineConfig, refine, search, search_config
from plad.rewrite.evaluate import Scorer, oriented
from plad.rewrite.insert import insert
from plad.rewrite.po import optimize
from plad.rewrite.prune import prune, remove
from plad.rewrite.swap import swap
from tests.conftest import REPO_ROOT

# programs per domain for the property tests (ShapeAssembly executes ~2 ms per program in Python)
SIZES = {"csg2d": 24, "csg3d": 16, "shapeassembly": 5}


def _execute(domain, programs):
    return domain.execute(pad_programs(programs))


def _random_targets(domain, n: int, rng: np.random.Generator) -> torch.Tensor:
    """Half executions of other random programs, half random blobs (thresholded smoothed noise)."""
    other = _execute(domain, domain.sample(n - n // 2, rng))
    noise = torch.from_numpy(rng.random((n // 2, *domain.shape)) < 0.5).float()
    for dim in range(1, noise.dim()):                 # box-blur every axis, so blobs have some extent
        noise = (noise + noise.roll(1, dim) + noise.roll(-1, dim)) / 3
    return torch.cat([other, noise > 0.5])


def _assert_not_worse(domain, before, before_values, after, after_values, targets):
    hib = domain.metric.higher_is_better
    o_before, o_after = oriented(before_values, hib), oriented(after_values, hib)
    assert bool((o_after <= o_before).all())
    same = o_after == o_before
    assert all(len(a) <= len(b) for a, b, s in zip(after, before, same.tolist()) if s)
    for p in after:
        domain.check(p)
    # the reported values are the domain's own executor and metric
    assert torch.equal(domain.metric(_execute(domain, after), targets), after_values)


@pytest.mark.parametrize("name", domain_names())
def test_no_rewrite_makes_a_program_worse(name):
    domain = get_domain(name)
    rng = np.random.default_rng(7)
    n = SIZES[name]
    programs = domain.sample(n, rng)
    targets = _random_targets(domain, n, rng)
    scorer = Scorer(domain, targets)
    values = scorer.values(programs)
    steps = {
        "po": lambda p, v: optimize(scorer, p, v, sweeps=1, wide=False),
        "prune": lambda p, v: prune(scorer, p, v),
        "insert": lambda p, v: insert(scorer, p, v)[:2],
        "swap": lambda p, v: swap(scorer, p, v, sweeps=2)[:2],
        "remove": lambda p, v: remove(scorer, p, v),
    }
    for step in steps.values():
        new, new_values = step(programs, values)
        _assert_not_worse(domain, programs, values, new, new_values, targets)
    result = refine(domain, programs, targets, RefineConfig(rounds=1, po_sweeps=1, wide=False, tune_sweeps=1))
    _assert_not_worse(domain, programs, values, result.programs, result.values, targets)
    result = refine(domain, programs, targets, RefineConfig(rounds=1, po_sweeps=1, wide=False, tune_sweeps=1,
                                                            swap=True))
    _assert_not_worse(domain, programs, values, result.programs, result.values, targets)
    result = refine(domain, programs, targets, RefineConfig(rounds=1, po_sweeps=1, wide=False, tune_sweeps=1,
                                                            insertions=3))
    _assert_not_worse(domain, programs, values, result.programs, result.values, targets)
    result = refine(domain, programs, targets, RefineConfig(rounds=1, po_sweeps=1, wide=False, tune_sweeps=1,
                                                            remove=True))
    _assert_not_worse(domain, programs, values, result.programs, result.values, targets)


# one-step perturbations: (cases, programs sampled with at most this many primitives/parts)
PERTURB = {"csg2d": 100, "csg3d": 100, "shapeassembly": 20}


@pytest.mark.parametrize("name", domain_names())
def test_po_recovers_one_step_perturbations(name):
    """PO (local moves) undoes one random local move in at least 90% of the cases."""
    domain = get_domain(name)
    space = domain.rewrite
    rng = np.random.default_rng(11)
    cases = PERTURB[name]
    originals = domain.sample(cases, rng)
    targets = _execute(domain, originals)
    perturbed = []
    for p in originals:
        slots = [s for block in space.blocks(p, wide=False) for s in block]
        slot = slots[rng.integers(len(slots))]
        q = list(p)
        q[slot.position] = slot.choices[rng.integers(len(slot.choices))]
        perturbed.append(q)
    scorer = Scorer(domain, targets)
    best = scorer.values(originals)          # CD 0 / IoU 1 (the target is the program's execution)
    values = scorer.values(perturbed)
    changed = values != best
    assert int(changed.sum()) >= cases // 2  # most perturbations change the shape
    _, recovered = optimize(scorer, perturbed, values, sweeps=4, wide=False)
    rate = float((recovered == best).double().mean())
    print(f"{name}: PO recovered {rate:.0%} of {cases} one-step perturbations ({int(changed.sum())} changed the shape)")
    assert rate >= 0.9


PRUNABLE = {
    # (program with a useless primitive, the program without it)
    "csg2d": ("s(32,32,24)c(32,32,8)+$", "s(32,32,24)$"),
    "csg3d": ("union cuboid 16 16 16 21 21 21 ellipsoid 16 16 16 5 5 5", "cuboid 16 16 16 21 21 21"),
}
EMPTY_NODE = {
    # an intersection of disjoint primitives (empty) under a union
    "csg2d": ("s(16,16,8)c(48,48,8)*s(32,32,24)+$", "s(32,32,24)$"),
    "csg3d": ("union inter cuboid 5 5 5 3 3 3 cuboid 25 25 25 3 3 3 cuboid 16 16 16 9 9 9",
              "cuboid 16 16 16 9 9 9"),
}


@pytest.mark.parametrize("cases", [PRUNABLE, EMPTY_NODE], ids=["contained", "empty"])
@pytest.mark.parametrize("name", sorted(PRUNABLE))
def test_pruning_removes_a_primitive_that_changes_nothing(name, cases):
    domain = get_domain(name)
    text, expected = cases[name]
    program = domain.parse(text)
    noise = torch.from_numpy(np.random.default_rng(3).random((1, *domain.shape)) < 0.3)
    for target in (_execute(domain, [program]), noise):
        scorer = Scorer(domain, target)
        values = scorer.values([program])
        pruned, new_values = prune(scorer, [program], values)
        assert domain.format(pruned[0]) == domain.format(domain.parse(expected))
        assert torch.equal(new_values, values)
        assert scorer.stats.counts["prune"] == 1


def test_top_down_pruning_keeps_the_best_sub_tree():
    domain = get_domain("csg3d")
    keep = "cuboid 10 10 10 5 5 5"
    program = domain.parse(f"union {keep} cuboid 24 24 24 5 5 5")
    target = _execute(domain, [domain.parse(keep)])
    scorer = Scorer(domain, target)
    pruned, values = prune(scorer, [program], scorer.values([program]))
    assert domain.format(pruned[0]) == keep and float(values[0]) == 1.0


TWO_PRIMITIVES = {
    "csg2d": ("s(24,24,12)c(40,40,12)+$", "s(24,24,12)$"),
    "csg3d": ("union cuboid 8 8 8 7 7 7 cuboid 22 20 20 9 11 7", "cuboid 8 8 8 7 7 7"),
    "shapeassembly": ("START 24 Cuboid 10 6 10 Attach bbox bot fpos_5_5 fpos_3_3 "
                      "Cuboid 8 8 8 Attach bbox top fpos_5_5 fpos_7_7 END",
                      "START 24 Cuboid 10 6 10 Attach bbox bot fpos_5_5 fpos_3_3 END"),
}


@pytest.mark.parametrize("name", domain_names())
def test_insertion_improves_an_empty_or_one_primitive_start(name):
    domain = get_domain(name)
    two, one = (domain.parse(t) for t in TWO_PRIMITIVES[name])
    target = _execute(domain, [two, two])
    scorer = Scorer(domain, target)
    starts = [[], one]
    values = scorer.values(starts)
    new, new_values, inserted = insert(scorer, starts, values)
    assert inserted.tolist() == [True, True]
    hib = domain.metric.higher_is_better
    assert bool((oriented(new_values, hib) < oriented(values, hib)).all())
    # two greedy insertions from scratch rebuild the two-primitive target exactly
    if name != "shapeassembly":
        result = search(domain, target[:1], search_config(domain, insertions=2, **{"refine.rounds": 0}))
        perfect = 0.0 if not hib else 1.0
        assert float(result.values[0]) == perfect


@pytest.mark.parametrize("name", domain_names())
def test_refinement_inserts_up_to_its_count_per_round(name):
    """``RefineConfig.insertions``: one round of refinement grows a program by that many primitives (parts), each
    kept because it improves; one insertion per round (the default) leaves a two-primitive target half built."""
    domain = get_domain(name)
    two = domain.parse(TWO_PRIMITIVES[name][0])
    target = _execute(domain, [two])
    cfg = {"rounds": 1, "po_sweeps": 0, "prune": False, "tune_sweeps": 10}
    once = refine(domain, [[]], target, RefineConfig(**cfg))
    twice = refine(domain, [[]], target, RefineConfig(insertions=2, **cfg))
    assert once.stats.as_dict()["accepted"]["insert"] == 1
    assert twice.stats.as_dict()["accepted"]["insert"] == 2
    hib = domain.metric.higher_is_better
    assert float(oriented(twice.values, hib)[0]) < float(oriented(once.values, hib)[0])
    assert torch.equal(domain.metric(_execute(domain, twice.programs), target), twice.values)
    if name != "shapeassembly":   # the two primitives rebuilt exactly
        assert float(twice.values[0]) == (1.0 if hib else 0.0)


SA_THREE = ("START 24 Cuboid 10 6 10 Attach bbox bot fpos_5_5 fpos_3_3 "
            "Cuboid 8 8 8 Attach bbox top fpos_5_5 fpos_7_7 "
            "Cuboid 4 4 4 Attach cube1 bot fpos_5_5 fpos_5_5 Reflect X END")


def test_shapeassembly_removals_renumber_later_references():
    """A part no later part attaches to may go (the later references renumbered); one attached to may not."""
    domain = get_domain("shapeassembly")
    program = domain.parse(SA_THREE)
    assert [domain.format(p) for p in domain.rewrite.removals(program)] == [
        # cube0 removed: the third part's reference cube1 becomes cube0
        "START 24 Cuboid 8 8 8 Attach bbox top fpos_5_5 fpos_7_7 "
        "Cuboid 4 4 4 Attach cube0 bot fpos_5_5 fpos_5_5 Reflect X END",
        # cube1 stays: the third part attaches to it; the last part goes with its symmetry
        "START 24 Cuboid 10 6 10 Attach bbox bot fpos_5_5 fpos_3_3 "
        "Cuboid 8 8 8 Attach bbox top fpos_5_5 fpos_7_7 END"]
    # each removal executes to the union of the other parts, as placed in the original program
    parts = [domain.parse(t) for t in (
        "START 24 Cuboid 10 6 10 Attach bbox bot fpos_5_5 fpos_3_3 END",
        "START 24 Cuboid 8 8 8 Attach bbox top fpos_5_5 fpos_7_7 END")]
    one, two = _execute(domain, parts)
    whole = _execute(domain, [program])[0]
    without0, without2 = _execute(domain, domain.rewrite.removals(program))
    assert torch.equal(without2, one | two)
    assert torch.equal(without0, whole & ~(one & ~two))
    assert domain.rewrite.removals(parts[0]) == []


@pytest.mark.parametrize("name", domain_names())
def test_removal_drops_a_wrong_primitive(name):
    """``remove``: a program that is its target's exact program plus a wrong primitive (part) loses it; one
    ``refine`` round with ``remove`` and nothing else does the same."""
    domain = get_domain(name)
    wrong = {"csg2d": "s(24,24,12)c(40,40,12)+t(48,16,8)+$",
             "csg3d": "union union cuboid 8 8 8 7 7 7 cuboid 22 20 20 9 11 7 cuboid 26 4 26 3 3 3",
             "shapeassembly": TWO_PRIMITIVES["shapeassembly"][0].replace(
                 " END", " Cuboid 4 30 4 Attach bbox left fpos_5_5 fpos_5_5 END")}[name]
    right = domain.parse(TWO_PRIMITIVES[name][0])
    program = domain.parse(wrong)
    target = _execute(domain, [right])
    scorer = Scorer(domain, target)
    new, values = remove(scorer, [program], scorer.values([program]))
    assert new == [right] and float(values[0]) == (1.0 if domain.metric.higher_is_better else 0.0)
    cfg = RefineConfig(rounds=1, po_sweeps=0, prune=False, insert=False, remove=True)
    assert refine(domain, [program], target, cfg).programs == [right]
    assert refine(domain, [program], target, RefineConfig(rounds=1, po_sweeps=0, prune=False,
                                                          insert=False)).programs == [program]


def test_swap_replaces_a_wrong_primitive_at_the_same_length():
    """Target: two boxes; program: one of them and a wrong box. Insertion would add the missing box beside the
    wrong one; a swap removes the wrong one and inserts the missing one in its place."""
    domain = get_domain("csg3d")
    a, b = "cuboid 8 8 8 7 7 7", "cuboid 22 22 22 9 9 9"
    target = _execute(domain, [domain.parse(f"union {a} {b}")])
    program = domain.parse(f"union {a} cuboid 22 6 26 5 5 5")
    assert [domain.format(p) for p in domain.rewrite.removals(program)] == ["cuboid 22 6 26 5 5 5", a]
    scorer = Scorer(domain, target)
    values = scorer.values([program])
    new, new_values, swapped = swap(scorer, [program], values, sweeps=10)
    assert swapped.tolist() == [True]
    assert float(new_values[0]) == 1.0 and len(new[0]) == len(program)
    assert torch.equal(domain.metric(_execute(domain, new), target), new_values)
    # nothing left to swap: the exact program stays as it is
    again, again_values, swapped = swap(scorer, new, new_values, sweeps=10)
    assert swapped.tolist() == [False] and again == new


def test_rewriters_are_generic():
    """Code outside plad/domains never names a domain."""
    root = REPO_ROOT / "plad" / "rewrite"
    for path in root.glob("*.py"):
        text = path.read_text()
        for name in domain_names():
            assert name not in text, f"{path.name} names the {name} domain"


def test_search_config_rejects_unknown_keys():
    from plad.config import ConfigError

    with pytest.raises(ConfigError, match="unknown key"):
        search_config(get_domain("csg2d"), sweeps=3)
