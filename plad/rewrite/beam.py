"""Beam search over partial programs, from the empty program.

At each step every program of the beam (``width`` per target) is extended by
the domain's candidate generator
(:meth:`~plad.domains.space.RewriteSpace.extensions`: one more primitive or
part, e.g. every draw token with every operator); of each program's children
the ``width`` best by the exact metric (after the domain's screen, if any)
survive, and of all survivors of a target the ``width`` best with distinct
executions form its next beam (no program has more than ``width`` children
among a target's ``width`` best, so keeping more per program would change
the beam only where children with the same execution were dropped). A child may be worse than its parent (a
primitive that a later difference carves), which is what a beam buys over
greedy insertion. Every program the beam has held is a candidate answer: the
``finals`` best with distinct executions, over all steps, are returned (with
their exact values) for refinement.

The programs of all beams of a batch of targets are extended, screened and
scored together, :data:`PROGRAMS_PER_CALL` programs per batched call of the
domain's executor and metric.
"""
from __future__ import annotations

import hashlib
import time

import numpy as np
import torch

from plad.rewrite.evaluate import Scorer, oriented

#: beam programs extended in one call of the candidate generator and the scorer (a 2D CSG program has 1,272
#: children): bounds the memory of a batch of many shapes; the result does not depend on it, since each
#: program's children are ranked on their own
PROGRAMS_PER_CALL = 64


def _keys(outputs: torch.Tensor) -> list[bytes]:
    """A digest of each execution (n, *shape) bool, to tell programs with the same output apart cheaply."""
    packed = np.packbits(outputs.reshape(outputs.shape[0], -1).numpy(), axis=1)
    return [hashlib.blake2b(row.tobytes(), digest_size=16).digest() for row in packed]


class _Found:
    """The ``size`` best programs (distinct executions) seen for one target: objective, then fewer tokens."""

    def __init__(self, size: int):
        self.size = size
        self.items: dict[bytes, tuple[float, int, list[int], float]] = {}

    def add(self, key: bytes, rank: float, program: list[int], value: float) -> None:
        old = self.items.get(key)
        if old is None or (rank, len(program)) < (old[0], old[1]):
            self.items[key] = (rank, len(program), program, value)
        if len(self.items) > 2 * self.size:             # trim now and then, not at every insertion
            self.trim()

    def trim(self) -> None:
        best = sorted(self.items.items(), key=lambda kv: (kv[1][0], kv[1][1]))[: self.size]
        self.items = dict(best)

    def best(self) -> list[tuple[list[int], float]]:
        self.trim()
        return [(p, v) for _, (_, _, p, v) in sorted(self.items.items(), key=lambda kv: (kv[1][0], kv[1][1]))]


def beam_search(scorer: Scorer, width: int, steps: int, finals: int = 1,
                deadline: float | None = None) -> list[list[tuple[list[int], float]]]:
    """Beam search for every target of ``scorer``; per target the ``finals`` best programs found
    (distinct executions), best first, each with its exact value. A target for which no extension
    exists gets an empty list.

    ``width``: programs kept per target and step;
    ``steps``: extensions from the empty program (fewer if the language's length cap ends them);
    ``deadline``: ``time.perf_counter()`` value after which no new step starts.
    """
    if width < 1 or finals < 1:
        raise ValueError(f"beam search: width {width} and finals {finals} must be at least 1")
    n = len(scorer.targets)
    hib = scorer.higher_is_better
    found = [_Found(finals) for _ in range(n)]
    beam: list[list[int]] = [[] for _ in range(n)]             # the programs of all beams
    target = np.arange(n)                                       # the target of each
    outputs = torch.zeros(n, *scorer.domain.shape, dtype=torch.bool)   # their executions
    for _ in range(steps):
        if not beam or (deadline is not None and time.perf_counter() > deadline):
            break
        children, parent, parts = [], [], []
        for start in range(0, len(beam), PROGRAMS_PER_CALL):
            sl = slice(start, start + PROGRAMS_PER_CALL)
            cands = scorer.space.extensions(beam[sl], outputs[sl], scorer.targets[target[sl]])
            if not len(cands):
                continue
            group = cands.owner.numpy()                             # the beam program each child extends
            cands.owner = torch.from_numpy(target[sl])[cands.owner]  # the target each child is scored against
            rows, values = scorer.top(cands, group, width)
            children += [cands.row(int(r)) for r in rows]
            parent.append(group[rows] + start)
            parts.append(values)
        if not children:
            break
        values = np.concatenate(parts)
        child_target = target[np.concatenate(parent)]
        child_outputs = scorer.outputs(children)
        keys = _keys(child_outputs)
        rank = oriented(torch.from_numpy(values), hib).numpy()
        lengths = np.array([len(c) for c in children])
        order = np.lexsort((np.arange(len(children)), lengths, rank, child_target))
        taken = np.zeros(n, dtype=np.int64)
        seen: set[tuple[int, bytes]] = set()
        picked = []
        for c in order.tolist():
            t = int(child_target[c])
            found[t].add(keys[c], float(rank[c]), children[c], float(values[c]))
            if (t, keys[c]) in seen or taken[t] >= width:
                continue
            seen.add((t, keys[c]))
            taken[t] += 1
            picked.append(c)
        beam = [children[c] for c in picked]
        target = child_target[picked]
        outputs = child_outputs[picked]
    return [f.best() for f in found]


__all__ = ["beam_search"]
