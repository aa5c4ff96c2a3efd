"""ShapeAssembly's own program edit for augmentation (:meth:`plad.domains.base.Domain.edits`): grafting a part.

The language has no expression tree to graft sub-expressions through (its rewrite space has no nodes), so
a graft takes a whole part of a donor program, ``Cuboid l h w MOVES [SYM]``, and puts it into the program
either in place of one of its parts or after its last one. The grafted part keeps its tokens; what it
attaches to is read in its new place: ``bbox`` stays the bbox, ``cube j`` is the program's own j-th cuboid,
so the part may only go where cuboid j is declared before it (the grammar's rule). Parts after a replaced
one keep their references, now to the grafted cuboid where they named the replaced one.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from plad.domains.shapeassembly.tokens import MAX_CUBOIDS, MAX_LEN, token_table


def parts(program: Sequence[int]) -> tuple[list[tuple[int, int]], int]:
    """(token spans [start, end) of the parts, position of END) of a valid program."""
    kind = [t.kind for t in token_table().tokens]
    starts = [pos for pos, t in enumerate(program) if kind[t] == "cuboid"]
    end = next((pos for pos, t in enumerate(program) if kind[t] == "end"), len(program))
    return list(zip(starts, starts[1:] + [end])), end


def graft(program: Sequence[int], donors: Sequence[Sequence[int]], rng: np.random.Generator) -> list[int] | None:
    """A part of a donor drawn from ``donors`` in place of one of the program's parts, or appended; None where
    the drawn part fits nowhere (it names a cuboid the program does not declare before it, or the result
    would pass 10 cuboids or 100 tokens)."""
    if not donors:
        return None
    table = token_table()
    donor = list(donors[int(rng.integers(len(donors)))])
    spans, _ = parts(donor)
    if not spans:
        return None
    a, b = spans[int(rng.integers(len(spans)))]
    part = donor[a:b]
    refs = [table.tokens[t].params[0] for t in part if table.tokens[t].kind == "cind"]
    need = max(refs, default=-1) + 1             # the grafted cuboid's index must be at least this
    own, end = parts(program)
    # (where it goes [start, end) of the program's tokens it replaces) for each index k it may take
    places = [own[k] for k in range(need, len(own))]
    if len(own) < MAX_CUBOIDS and need <= len(own):
        places.append((end, end))
    places = [(s, e) for s, e in places if len(program) - (e - s) + len(part) <= MAX_LEN]
    if not places:
        return None
    s, e = places[int(rng.integers(len(places)))]
    return list(program[:s]) + part + list(program[e:])
