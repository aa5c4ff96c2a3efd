"""The stratified rejection loop the samplers share: quotas per stratum, rejection, rates, seeding."""
import numpy as np

from plad.domains.synthetic import stratified_rejection_sample


def run(n, seed, calls=None):
    """Programs [k, x]: x a random draw; a candidate is accepted when x is even (about half)."""
    def propose(wanted, rates, rng):
        if calls is not None:
            calls.append((dict(wanted), dict(rates)))
        ks = [k for k, missing in wanted.items() for _ in range(missing)]
        return ks, [[k, int(x)] for k, x in zip(ks, rng.integers(0, 1000, size=len(ks)))]

    def accept(programs):
        return [p[1] % 2 == 0 for p in programs]

    return stratified_rejection_sample(n, np.random.default_rng(seed), range(2, 6), propose, accept)


def test_quotas_per_stratum_are_the_uniform_draw_and_only_accepted_programs_are_kept():
    out = run(500, seed=3)
    quotas = np.bincount(np.random.default_rng(3).integers(2, 6, size=500), minlength=6)
    assert len(out) == 500 and all(p[1] % 2 == 0 for p in out)
    assert np.array_equal(np.bincount([p[0] for p in out], minlength=6), quotas)
    assert [p[0] for p in out] != sorted(p[0] for p in out)     # shuffled, not grouped by stratum


def test_seeded_and_rates_follow_the_last_batch():
    assert run(200, seed=1) == run(200, seed=1) and run(200, seed=1) != run(200, seed=2)
    calls = []
    run(200, seed=1, calls=calls)
    assert len(calls) > 1 and all(r == 0.5 for r in calls[0][1].values())
    # each later batch asks only for what is still missing, with rates near the 1/2 acceptance
    for (before, _), (after, rates) in zip(calls, calls[1:]):
        assert set(after) <= set(before) and all(after[k] <= before[k] for k in after)
        assert all(0 < rates[k] <= 1 for k in after)
