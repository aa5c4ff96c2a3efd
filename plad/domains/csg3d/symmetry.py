"""The symmetries of 3D CSG: quarter turns about the vertical axis and the mirrors through vertical planes.

The vertical axis is y (grid axis 1): the real shapes are PartNet's, voxelized on the same [x, y, z] grid
with y up (docs/shapeassembly.md, "Voxelizing a real shape"). The eight symmetries of the horizontal square
(x, z) keep "up": ``mirror_x``, ``mirror_z``, ``turn_180``, the quarter turns ``turn_90`` and ``turn_270``
(order 4), and the mirrors through the diagonal planes ``swap_xz`` and ``swap_xz_mirrored``.

All are exact. Voxel i of a reversed axis becomes voxel 31 - i, and a primitive's centre c on that axis
becomes 31 - c: the inside tests (``|p - c| <= d/2`` for a cuboid, the sum of squares for an ellipsoid)
only see ``p - c``, which the map negates, and swapping x and z swaps the matching centre and extent
parameters; operators stay. So every primitive, and every boolean combination, executes to exactly the
transformed grid. A centre of 31 on a reversed axis would become 0, outside the parameter range 1..31:
such a program maps to None (the sampler's centres lie in 2..30; the search's own primitives seldom sit
on the last voxel plane).

Left out: the mirror that turns a shape upside down (y -> 31 - y) is as exact, but the real shapes are
furniture standing on its floor, and the stream is meant to stay near their distribution.
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np

from plad.domains.base import Symmetry
from plad.domains.csg3d.tokens import N_PARAMS, PARAM_MAX, PARAM_MIN, RES, token_table

#: (name, axes, flips) on the grid axes (x, y, z): axis i of the result is axis ``axes[i]`` of the original,
#: reversed where ``flips[i]``; y (axis 1) always stays
_GROUP = (
    ("mirror_x", (0, 1, 2), (True, False, False)),
    ("mirror_z", (0, 1, 2), (False, False, True)),
    ("turn_180", (0, 1, 2), (True, False, True)),
    ("turn_90", (2, 1, 0), (True, False, False)),
    ("turn_270", (2, 1, 0), (False, False, True)),
    ("swap_xz", (2, 1, 0), (False, False, False)),
    ("swap_xz_mirrored", (2, 1, 0), (True, False, True)),
)


@lru_cache(maxsize=1)
def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(is a primitive token (V,), the value of each number token (V,) (0 for others), value -> token id)."""
    table = token_table()
    prim = np.array([t.kind == "primitive" for t in table.tokens])
    value = np.array([t.params[0] if t.kind == "num" else 0 for t in table.tokens], dtype=np.int64)
    num = np.full(RES + 1, -1, dtype=np.int64)
    for i, t in enumerate(table.tokens):
        if t.kind == "num":
            num[t.params[0]] = i
    return prim, value, num


def _mapper(axes: tuple[int, ...], flips: tuple[bool, ...]):
    def program(ids: Sequence[int]) -> list[int] | None:
        prim, value, num = _tables()
        ids = np.asarray(ids, dtype=np.int64)
        starts = np.flatnonzero(prim[ids])                               # primitive tokens
        params = value[ids[starts[:, None] + 1 + np.arange(N_PARAMS)]]   # (P, 6): centre xyz, extents xyz
        centre, extent = params[:, :3], params[:, 3:]
        new_centre = np.stack([RES - 1 - centre[:, a] if f else centre[:, a] for a, f in zip(axes, flips)], 1)
        new_extent = extent[:, list(axes)]
        new = np.concatenate([new_centre, new_extent], 1)
        if ((new < PARAM_MIN) | (new > PARAM_MAX)).any():
            return None
        out = ids.copy()
        out[starts[:, None] + 1 + np.arange(N_PARAMS)] = num[new]
        return out.tolist()

    return program


@lru_cache(maxsize=1)
def symmetries() -> tuple[Symmetry, ...]:
    return tuple(Symmetry(name, _mapper(axes, flips), axes, flips) for name, axes, flips in _GROUP)
