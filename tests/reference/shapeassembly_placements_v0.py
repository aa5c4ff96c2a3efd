"""Frozen copy of ShapeAssemblyRewrite._placements before it cached the per-cuboid moves and computed the norms
without np.linalg.norm's checks (commit 8d2906d): the reference the fast one must equal value for value."""
from __future__ import annotations

import numpy as np

from plad.domains.shapeassembly.rewrite import _FACE_AXIS, _GRID
from plad.domains.shapeassembly.tokens import FACE_TOKENS, FPOS, attach_points


def placements(cuboids, dims: np.ndarray, center: np.ndarray) -> list[tuple[float, list[str]]]:
    out = []
    for name, pos, axes, bdims in cuboids:
        for face in FACE_TOKENS:
            axis = _FACE_AXIS[face]
            q1, q2 = attach_points(face, name == "bbox", (0.5, 0.5), (0.5, 0.5))
            resid = pos + ((np.array(q2) - 0.5) * bdims) @ axes - (np.array(q1) - 0.5) * dims - center
            choice = []
            for a in (b for b in range(3) if b != axis):
                shift = np.repeat(((_GRID - 0.5) * bdims[a])[:, None] * axes[a][None, :], 9, 0)
                shift = shift.reshape(9, 9, 3).transpose(1, 0, 2).copy()
                shift[:, :, a] -= ((_GRID - 0.5) * dims[a])[:, None]
                cost = np.linalg.norm(resid + shift, axis=2)
                i1, i2 = np.unravel_index(int(cost.argmin()), cost.shape)
                resid = resid + shift[i1, i2]
                choice.append((FPOS[i1], FPOS[i2]))
            (m1, t1), (m2, t2) = choice
            out.append((float(np.linalg.norm(resid)), ["Attach", name, face, f"fpos_{m1}_{m2}", f"fpos_{t1}_{t2}"]))
    out.sort(key=lambda x: x[0])
    return out
