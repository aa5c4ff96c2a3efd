"""The 3D CSG executor's CPU path compiled with numba: the same stack machine and primitives, the same bits.

:meth:`plad.domains.csg3d.executor.Executor._run_each` runs programs one at a time in Python (a parse per token,
a numpy operation per stack step, a dictionary of rendered primitives); here the whole loop is one compiled
call per batch: each row is parsed with the executor's own tables (``delta``, ``code``, ``value``, ``ell``,
``fixed``), its primitives rendered into the stack directly (integer arithmetic only, as
:func:`~plad.domains.csg3d.executor.render_primitives`: a cuboid's columns from the interval table, an
ellipsoid's from ``R = D - t_x - t_y`` and the column table) and combined as the executor combines them
(``A | B``, ``A & B``, ``A & ~B`` with A the top). No rounding anywhere, so the words equal the tensor path's;
``tests/plad/domains/csg3d/test_compiled.py`` compares them on sampled programs, every primitive kind and the
pseudo primitives. :func:`unpack_into` is :func:`~plad.domains.csg3d.executor.unpack`'s byte table in a loop.
"""
from __future__ import annotations

import numpy as np

from plad.jit import compiler

njit = compiler()   # None without numba: the caller keeps its tensor path

__all__ = ["available", "run_programs", "unpack_into"]

def available() -> bool:
    """Whether the kernels can run here (numba importable)."""
    return njit is not None


#: run_programs' answers: every row ran, or some row needs the executor's batched path (it does not end within
#: its length, holds a token beyond the tables, or gives a primitive a parameter that is no number)
DONE, FALLBACK = 0, 1

if njit is not None:
    from plad.domains.csg3d.tokens import N_PARAMS, RES

    _WORDS = RES * RES
    _N_COLUMN = (RES - 1) ** 2 // 4 + 2          # the column table's row length (_N_MAX + 2)
    # step codes, as plad.domains.csg3d.executor's
    _NOOP, _PRIM, _UNION, _INTER, _DIFF = 0, 1, 2, 3, 4

    @njit(cache=True, nogil=True)
    def _render(row, i, value, ell, fixed, interval, column, dst):
        """The primitive whose token is row[i] into dst (int32 (1024,)); False where a parameter is no number."""
        tok = row[i]
        cx, cy, cz = value[row[i + 1]], value[row[i + 2]], value[row[i + 3]]
        dx, dy, dz = value[row[i + 4]], value[row[i + 5]], value[row[i + 6]]
        f = fixed[tok]
        if f == 1:
            dst[:] = 0
            return True
        if f == 2:
            dst[:] = -1
            return True
        if dx <= 0 or dy <= 0 or dz <= 0 or cx < 0 or cy < 0 or cz < 0 or cz >= RES:
            return False                          # not a number token (values are 1 .. 31)
        if not ell[tok]:
            # |p_i - c_i| <= d_i / 2 on every axis: the z interval of c_z -+ floor(d_z / 2), clipped
            lo = min(max(cz - dz // 2, 0), RES)
            hi1 = min(max(cz + dz // 2 + 1, 0), RES)
            word = interval[lo * (RES + 1) + hi1]
            for x in range(RES):
                in_x = 2 * abs(x - cx) <= dx
                for y in range(RES):
                    dst[x * RES + y] = word if in_x and 2 * abs(y - cy) <= dy else 0
            return True
        # sum_i 4 (p_i - c_i)^2 D / d_i^2 <= D with D = dx^2 dy^2 dz^2; a term above D is capped at D + 1
        dx2, dy2, dz2 = dx * dx, dy * dy, dz * dz
        big = dx2 * dy2 * dz2
        wx, wy = big // dx2, big // dy2
        q = 4 * (big // dz2)
        base = cz * _N_COLUMN + 1
        ty = np.empty(RES, dtype=np.int64)
        for y in range(RES):
            ty[y] = min(4 * (y - cy) * (y - cy) * wy, big + 1)
        for x in range(RES):
            tx = min(4 * (x - cx) * (x - cx) * wx, big + 1)
            for y in range(RES):
                r = big - tx - ty[y]
                if r < -1:
                    r = -1
                dst[x * RES + y] = column[base + r // q]
        return True

    @njit(cache=True, nogil=True)
    def run_programs(rows, delta, code, value, ell, fixed, interval, column, check_degenerate, out, flags):
        """rows int64 (B, L) (clamped at 0; a program and any padding) -> out int32 (B, 1024), flags bool (B,).

        Returns DONE, or FALLBACK as soon as a row cannot run here (out is then incomplete)."""
        n_rows, width = rows.shape
        vocab = delta.shape[0]
        steps = np.empty(width, dtype=np.int64)       # per step: -1 - token index of a primitive, or an op code
        stack = np.empty((width // (N_PARAMS + 1) + 2, _WORDS), dtype=np.int32)
        for r in range(n_rows):
            row = rows[r]
            n = width
            need, i, k = 1, 0, 0
            while need > 0:
                if i >= n:
                    return FALLBACK
                tok = row[i]
                if tok >= vocab:
                    return FALLBACK
                need += delta[tok]
                c = code[tok]
                if c == _PRIM:
                    if i + N_PARAMS >= n:
                        return FALLBACK
                    for j in range(1, N_PARAMS + 1):
                        if row[i + j] >= vocab:
                            return FALLBACK
                    steps[k] = -1 - i
                    k += 1
                elif c != _NOOP:
                    steps[k] = c
                    k += 1
                i += 1
            top = 0
            flagged = False
            for s in range(k - 1, -1, -1):               # prefix read right to left: a stack machine
                step = steps[s]
                if step < 0:
                    if not _render(row, -1 - step, value, ell, fixed, interval, column, stack[top]):
                        return FALLBACK
                    top += 1
                    continue
                a = stack[top - 1]                       # the first operand: the top
                b = stack[top - 2]
                same_a, same_b, empty = True, True, True
                for w in range(_WORDS):
                    if step == _UNION:
                        v = a[w] | b[w]
                    elif step == _INTER:
                        v = a[w] & b[w]
                    else:
                        v = a[w] & ~b[w]
                    same_a &= v == a[w]
                    same_b &= v == b[w]
                    empty &= v == 0
                    b[w] = v                             # b's slot becomes the result's
                if check_degenerate and not flagged:
                    flagged = same_a or same_b or empty
                top -= 1
            out[r, :] = stack[top - 1]
            flags[r] = flagged
        return DONE

    @njit(cache=True, nogil=True)
    def unpack_into(as_bytes, table, out):
        """as_bytes uint8 (n,): the words' bytes, low byte first; table int64 (256,): a byte's 8 bits as 8 bytes
        of 0/1; out int64 (n,): the bool grids viewed as 8 voxels per int64."""
        for k in range(as_bytes.shape[0]):
            out[k] = table[as_bytes[k]]
