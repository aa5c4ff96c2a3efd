"""The one-box floor of ShapeAssembly: one cuboid centred in the bbox, sized to the target's tight box.

Real shapes are normalized by the tight bounds of their cuboids, so they are
centred in the grid (docs/shapeassembly.md); the program
``START h Cuboid l h w Attach bbox top fpos_5_5 fpos_5_5 END`` hangs a cuboid
from the centre of the bbox top, and with the bbox as tall as the cuboid it
is centred too. Its dimensions are the target's occupied voxel extents
(one token = one voxel = 1/32); the extents one voxel smaller and larger
are tried as well, and the program with the best IoU is kept.
"""
from __future__ import annotations

import itertools

import numpy as np
import torch

from plad.domains.shapeassembly.tokens import RES
from plad.metrics import iou


def box_program(l: int, h: int, w: int) -> str:   # noqa: E741  (l: length, the language's name)
    return f"START {h} Cuboid {l} {h} {w} Attach bbox top fpos_5_5 fpos_5_5 END"


def one_box(domain, targets: np.ndarray) -> list[list[int]]:
    """Per target (bool (N, 32, 32, 32) [x, y, z]) the best centred one-box program (token ids)."""
    out = []
    for target in targets:
        extents = []
        for a in range(3):
            occupied = np.nonzero(target.any(axis=tuple(b for b in range(3) if b != a)))[0]
            e = int(occupied[-1] - occupied[0] + 1) if len(occupied) else 1
            extents.append(sorted({min(max(e + k, 1), RES - 1) for k in (-1, 0, 1)}))
        programs = [domain.parse(box_program(*dims)) for dims in itertools.product(*extents)]
        grids = domain.execute(torch.tensor(programs))
        values = iou(grids, torch.from_numpy(target)[None].expand_as(grids))
        out.append(programs[int(values.argmax())])
    return out
