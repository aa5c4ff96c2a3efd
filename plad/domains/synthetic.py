"""The stratified rejection loop that every domain's synthetic sampler runs.

A sampler draws programs per stratum k, a structural size (primitives, parts),
with the same expected number for every k: each of the ``n`` programs gets a
k uniformly at random, then candidates of the strata still short are proposed
in batches, executed together and filtered until every stratum has its quota.
Filtering programs of a uniform k directly would skew the sizes, because
larger programs are rejected more often.

A sampler supplies only its domain parts: how candidates of given strata are
drawn (``propose``) and which candidates are kept (``accept``). The random
draws happen in a fixed order (quotas, then each batch's proposals, then the
final shuffle), so a seed gives the same programs.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

#: propose(wanted, rates, rng) -> (strata, programs): candidate programs (token ids) with the stratum of
#: each; ``wanted`` maps each stratum still short to how many programs it lacks (in stratum order),
#: ``rates`` each stratum to its acceptance rate in the last batch that tried it
Propose = Callable[[dict[int, int], dict[int, float], np.random.Generator], tuple[list[int], list[list[int]]]]
#: accept(programs) -> whether each candidate is kept (e.g. it executes to a non-degenerate shape)
Accept = Callable[[list[list[int]]], Sequence[bool]]


def stratified_rejection_sample(n: int, rng: np.random.Generator, strata: range, propose: Propose,
                                accept: Accept, initial_rate: float = 0.5) -> list[list[int]]:
    """``n`` accepted programs, uniform over the strata ``strata`` (a ``range``), in random order.

    ``initial_rate`` is the acceptance rate ``propose`` sees for a stratum before any batch tried it.
    """
    counts = np.bincount(rng.integers(strata.start, strata.stop, size=n), minlength=strata.stop)
    kept: dict[int, list[list[int]]] = {k: [] for k in strata}
    rates = {k: initial_rate for k in strata}
    while True:
        wanted = {k: int(counts[k]) - len(kept[k]) for k in kept if counts[k] > len(kept[k])}
        if not wanted:
            break
        ks, programs = propose(wanted, rates, rng)
        good = accept(programs)
        tried = dict.fromkeys(wanted, 0)
        passed = dict.fromkeys(wanted, 0)
        for k, program, ok in zip(ks, programs, good):
            tried[k] += 1
            if ok:
                passed[k] += 1
                if len(kept[k]) < counts[k]:
                    kept[k].append(program)
        for k in wanted:
            if tried[k]:
                # at least one success counted, so a stratum never looks hopeless
                rates[k] = max(passed[k], 1) / tried[k]
    out = [p for k in kept for p in kept[k]]
    return [out[i] for i in rng.permutation(len(out))]


__all__ = ["Accept", "Propose", "stratified_rejection_sample"]
