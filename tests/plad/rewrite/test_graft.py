"""Code grafting (plad.rewrite.graft): the desired execution is exact, a graft finds a part another program
holds, and no graft makes a program worse."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plad.config import ConfigError
from plad.domains import domain_names, get_domain
from plad.domains.base import pad_programs
from plad.rewrite import RefineConfig, refine, search_config
from plad.rewrite.evaluate import Scorer, oriented
from plad.rewrite.graft import Library, desired, graft

GRAFTING = [n for n in domain_names() if get_domain(n).rewrite is not None and get_domain(n).rewrite.grafts]


def _execute(domain, programs):
    return domain.execute(pad_programs(programs))


def test_the_tree_domains_graft():
    assert GRAFTING == ["csg2d", "csg3d"]


@pytest.mark.parametrize("name", GRAFTING)
def test_desired_execution_is_exact(name):
    """Replacing a node's sub-expression by any other changes the program's execution only where the node's
    ``care`` mask is set, and there the program matches the target exactly where the new sub-expression matches
    ``want``."""
    domain = get_domain(name)
    space = domain.rewrite
    rng = np.random.default_rng(3)
    programs = domain.sample(12, rng)
    donors = domain.sample(12, rng)
    targets = _execute(domain, domain.sample(12, rng))
    checked = 0
    for program, donor, target in zip(programs, donors, targets):
        nodes = space.nodes(program)
        outputs = _execute(domain, [space.standalone(program, n) for n in nodes])
        want, care = desired(space, program, nodes, outputs, target)
        root = _execute(domain, [program])[0].reshape(-1)
        donor_nodes = space.nodes(donor)
        for n, node in enumerate(nodes):
            piece = space.standalone(donor, donor_nodes[int(rng.integers(len(donor_nodes)))])
            new = space.splice(program, node, piece)
            if len(new) > space.max_len:
                continue
            domain.check(new)
            out = _execute(domain, [new])[0].reshape(-1)
            piece_out = _execute(domain, [piece])[0].reshape(-1)
            c = care[n]
            assert torch.equal(out[~c], root[~c])
            assert torch.equal((out == target.reshape(-1))[c], (piece_out == want[n])[c])
            checked += 1
    assert checked > 50


def test_a_graft_takes_the_part_another_program_holds():
    """2D: the target is A + (B - C); the program A + D lacks the difference, which the other program of the
    batch holds; one graft makes the program exact, its children are grafted from the library."""
    domain = get_domain("csg2d")
    a, b, c, d, x = "c(16,16,12)", "s(40,40,16)", "c(40,40,8)", "t(48,16,8)", "s(16,48,8)"
    wrong = domain.parse(f"{a}{d}+$")
    donor = domain.parse(f"{x}{b}{c}-+$")
    targets = _execute(domain, [domain.parse(f"{a}{b}{c}-+$"), donor])
    scorer = Scorer(domain, targets)
    values = scorer.values([wrong, donor])
    programs, new_values = graft(scorer, [wrong, donor], values)
    assert domain.format(programs[0]) == f"{a}{b}{c}-+$"
    assert float(new_values[0]) == 0.0
    assert programs[1] == donor
    assert scorer.stats.counts["graft"] == 1


def test_library_keeps_one_shortest_expression_per_execution():
    domain = get_domain("csg2d")
    square = "s(32,32,8)"
    programs = [domain.parse(f"{square}$"), domain.parse(f"{square}{square}+$"), domain.parse("c(16,16,8)$")]
    outputs = _execute(domain, programs)
    lib = Library.build(programs, outputs)
    assert [domain.format(p) for p in lib.programs] == [f"{square}$", "c(16,16,8)$"]
    # nearest by the masked Hamming distance: the circle's own execution, cared for everywhere, is entry 1
    want = outputs[2].reshape(1, -1)
    assert lib.nearest(want, torch.ones_like(want), 2).tolist() == [[1, 0]]
    # where nothing is cared for, every entry is at distance 0 (ties: the first)
    assert lib.nearest(want, torch.zeros_like(want), 1).tolist() == [[0]]


@pytest.mark.parametrize("name", GRAFTING)
def test_grafting_never_makes_a_program_worse(name):
    domain = get_domain(name)
    rng = np.random.default_rng(11)
    n = 16 if name == "csg2d" else 6         # a 3D CSG graft scores its candidates on 32^3 grids: keep it small
    programs = domain.sample(n, rng)
    targets = _execute(domain, domain.sample(n, rng))
    scorer = Scorer(domain, targets)
    values = scorer.values(programs)
    new, new_values = graft(scorer, programs, values, k=5)
    hib = domain.metric.higher_is_better
    assert bool((oriented(new_values, hib) <= oriented(values, hib)).all())
    assert torch.equal(domain.metric(_execute(domain, new), targets), new_values)
    assert all(len(p) <= domain.rewrite.max_len for p in new)
    result = refine(domain, programs, targets, RefineConfig(rounds=1, po_sweeps=0, insert=False, prune=False,
                                                            graft=5))
    assert bool((oriented(result.values, hib) <= oriented(values, hib)).all())
    assert "graft" in result.stats.counts


def test_grafting_without_boolean_operators_is_a_one_line_error():
    domain = get_domain("shapeassembly")
    with pytest.raises(ConfigError, match="shapeassembly domain has no expression tree"):
        search_config(domain, **{"refine.graft": 15})
    with pytest.raises(ValueError, match="no expression tree"):
        refine(domain, [[]], torch.zeros(1, *domain.shape, dtype=torch.bool), RefineConfig(graft=15))
    with pytest.raises(ConfigError, match="refine.graft = -1"):
        search_config(get_domain("csg2d"), **{"refine.graft": -1})


def test_a_library_file_lends_parts_no_program_of_the_batch_holds(tmp_path):
    """The same graft as above with the donor only in a saved library (as one shipped with a model)."""
    from plad.rewrite.graft import sub_expressions

    domain = get_domain("csg2d")
    a, b, c, d, x = "c(16,16,12)", "s(40,40,16)", "c(40,40,8)", "t(48,16,8)", "s(16,48,8)"
    library = sub_expressions(domain, [domain.parse(f"{x}{b}{c}-+$")])
    # the donor's 5 sub-expressions: s(16,48,8), b, c, b - c, x + (b - c)
    assert len(library) == 5
    path = tmp_path / "lib.npz"
    library.save(path, domain)
    loaded = Library.load(path, domain)
    assert loaded.programs == library.programs and torch.equal(loaded.executions, library.executions)
    wrong = domain.parse(f"{a}{d}+$")
    scorer = Scorer(domain, _execute(domain, [domain.parse(f"{a}{b}{c}-+$")]))
    alone, alone_values = graft(scorer, [wrong], scorer.values([wrong]))
    assert float(alone_values[0]) > 0.0           # its own sub-expressions cannot make the difference
    programs, values = graft(scorer, [wrong], scorer.values([wrong]), extra=loaded)
    assert domain.format(programs[0]) == f"{a}{b}{c}-+$" and float(values[0]) == 0.0
    result = refine(domain, [wrong], scorer.targets, RefineConfig(rounds=1, graft=15, graft_library=str(path)))
    assert float(result.values[0]) == 0.0


def test_a_bad_library_is_a_one_line_error_naming_the_file(tmp_path):
    from plad.rewrite.graft import sub_expressions

    csg2d, csg3d = get_domain("csg2d"), get_domain("csg3d")
    other = tmp_path / "csg3d.npz"
    sub_expressions(csg3d, csg3d.sample(2, np.random.default_rng(0))).save(other, csg3d)
    with pytest.raises(ValueError, match=f"{other}: a grafting library of csg3d, not of csg2d"):
        Library.load(other, csg2d)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=f"{garbage}: not a grafting library"):
        Library.load(garbage, csg2d)
    with pytest.raises(ConfigError, match=f"{garbage}: not a grafting library"):   # at configuration, not mid-search
        search_config(csg2d, **{"refine.graft_library": str(garbage)})
    with pytest.raises(ConfigError, match="graft_library = nowhere.npz: no such file"):
        search_config(csg2d, **{"refine.graft_library": "nowhere.npz"})
    with pytest.raises(ConfigError, match="csg3d ships no grafting library"):
        search_config(csg3d, **{"refine.graft": 15, "refine.graft_library": "shipped"})


def test_2d_search_levels_graft_from_the_shipped_library():
    domain = get_domain("csg2d")
    for effort in ("fast", "default", "best"):
        config = search_config(domain, effort=effort)
        assert (config.refine.graft, config.refine.graft_library) == (15, "shipped")
