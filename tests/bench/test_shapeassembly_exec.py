"""bench.shapeassembly_exec: its identity checks see equal outputs as equal and a changed one as changed, and
the replayed batches and a whole search are identical under the original and the fast executor."""
from __future__ import annotations

from bench import shapeassembly_exec
from plad.domains import get_domain
from tests.grammar import masked_rollouts

DOMAIN = get_domain("shapeassembly")


def test_replayed_batches_are_identical():
    programs = masked_rollouts(DOMAIN, 120, seed=11)
    batches = [programs[i:i + 40] for i in range(0, len(programs), 40)]
    old, new, identical = shapeassembly_exec.time_batches(DOMAIN, batches, repeats=1)
    assert identical and old > 0 and new > 0


def test_a_changed_output_is_not_identical():
    out = DOMAIN.run_batch(masked_rollouts(DOMAIN, 8, seed=12))
    assert shapeassembly_exec.same_outputs(out, tuple(t.clone() for t in out))
    grids = out[0].clone()
    grids[0, 0, 0, 0] = ~grids[0, 0, 0, 0]
    assert not shapeassembly_exec.same_outputs(out, (grids, *out[1:]))
    assert not shapeassembly_exec.same_outputs(out, (out[0], out[1].int(), *out[2:]))


def test_a_search_finds_the_same_programs_with_either_executor():
    own = type(DOMAIN).run_batch
    targets = DOMAIN.run_batch(masked_rollouts(DOMAIN, 2, seed=13))[0]
    old, new, identical = shapeassembly_exec.time_search(DOMAIN, targets, "fast")
    assert identical and old > 0 and new > 0
    assert type(DOMAIN).run_batch is own           # the original executor was only swapped in for the timing
