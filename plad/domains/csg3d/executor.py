"""Batched 3D CSG executor on bit-packed 32^3 grids (torch; CPU or CUDA).

Representation: a shape is a (32, 32) grid of int32 words ``W[x, y]`` whose
bit z is voxel [x, y, z] (all 32 bits used; bit 31 is the sign bit, which
bitwise operations do not care about). A Boolean operation on two shapes is
1024 word operations instead of 32768 bool ones.

Primitives, exactly as the inside tests of docs/domains.md with voxel center p = (x, y, z)
in index units: every column (x, y) of a cuboid or an ellipsoid is one
interval of z symmetric about c_z, so a primitive is rendered per column and
its z bits come from a lookup table. Everything is integer arithmetic, so
there is no rounding anywhere:

* cuboid ``max_i(|p_i - c_i| - d_i/2) <= 0``  <=>  ``2|p_i - c_i| <= d_i`` for
  every axis: the columns inside in x and y all hold the same word, the z
  interval ``|z - c_z| <= d_z/2``;
* ellipsoid ``sum_i((p_i - c_i) / (d_i/2))^2 <= 1``; multiplied by
  ``D = dx^2 dy^2 dz^2`` (<= 31^6 < 2^31) it reads
  ``sum_i 4 (p_i - c_i)^2 D / d_i^2 <= D``. With ``R(x, y) = D - t_x - t_y``
  and ``q = 4 dx^2 dy^2``, voxel z is inside iff ``q (z - c_z)^2 <= R``, i.e.
  ``(z - c_z)^2 <= n`` with ``n = floor(R / q)`` (R >= 0). n is at most
  ``floor(31^2 / 4) = 240``, so a (c_z, n) table gives the column word.

Programs are prefix. Read right to left, a prefix program is a postfix one
with the operands swapped, so each program runs as a stack machine over its
primitives and operators taken in reverse order: a primitive pushes its
grid; an operator pops A (the top: its first operand) and B and pushes
``A | B``, ``A & B`` or ``A & ~B``. All programs of a batch take these steps
together (rows sorted by step count, so the running rows are a prefix); a
program's stack is a (depth, 1024) slice of one int32 tensor.
"""
from __future__ import annotations

import functools
import sys

import numpy as np
import torch

from plad.domains.csg3d.tokens import N_PARAMS, RES, token_table
from plad.domains.grammar import TokenTable

# step codes of the reversed structural sequence
_NOOP, _PRIM, _UNION, _INTER, _DIFF = 0, 1, 2, 3, 4
_WORDS = RES * RES
#: largest n = floor(R / q) of an ellipsoid column: floor(d_z^2 / 4) for d_z <= 31
_N_MAX = (RES - 1) ** 2 // 4


def _interval_lut() -> np.ndarray:
    """(33, 33) uint32: entry [lo, hi1] has bits lo .. hi1-1 set (zero when hi1 <= lo)."""
    lut = np.zeros((RES + 1, RES + 1), dtype=np.uint64)
    for lo in range(RES + 1):
        for hi1 in range(lo + 1, RES + 1):
            lut[lo, hi1] = ((1 << hi1) - 1) ^ ((1 << lo) - 1)
    return lut.astype(np.uint32)


def _column_lut() -> np.ndarray:
    """(32, _N_MAX + 2) uint32: entry [c_z, n + 1] is the word of the z with
    ``(z - c_z)^2 <= n`` clipped to the grid (n = -1: no voxel)."""
    interval = _interval_lut()
    out = np.zeros((RES, _N_MAX + 2), dtype=np.uint32)
    for cz in range(RES):
        for n in range(_N_MAX + 1):
            k = int(np.sqrt(n))
            k -= k * k > n                      # exact integer square root, whatever sqrt rounds to
            k += (k + 1) * (k + 1) <= n
            out[cz, n + 1] = interval[max(cz - k, 0), min(cz + k + 1, RES)]
    return out


def _as_int32(words: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(words, dtype=np.uint32).view(np.int32))


_BYTE_BITS: dict[torch.device, torch.Tensor] = {}

#: on the CPU, the per-program path and unpack run as compiled kernels (plad.domains.csg3d.compiled) where numba
#: is installed, the same bits: None when the process has earned it (plad.jit), True from the first call, False
#: never (the numpy and torch paths)
_COMPILED: bool | None = None
#: the numpy path's CPU seconds per program and unpack's per grid, for plad.jit's rule
_NUMPY_PROGRAM_SECONDS = 7e-5
_UNPACK_GRID_SECONDS = 3e-5


def _compiled(device: torch.device, seconds: float):
    """plad.domains.csg3d.compiled where it applies (CPU, numba importable, plad.jit's rule for a call whose
    numpy or torch path takes about ``seconds``), else None."""
    from plad import jit

    return jit.kernels("plad.domains.csg3d.compiled", _COMPILED, seconds) if device.type == "cpu" else None


def unpack(words: torch.Tensor) -> torch.Tensor:
    """int32 (..., 32, 32) words -> bool (..., 32, 32, 32) indexed [x, y, z].

    Byte-wise: each byte of a word (little-endian: byte j holds z = 8j .. 8j+7)
    indexes a table of its 8 bits stored as 8 bytes of 0/1 in one int64, so the
    output is written once, without (..., 32) int32 temporaries.
    """
    dev = words.device
    if sys.byteorder != "little":  # torch views memory in the machine's byte order
        raise NotImplementedError("csg3d unpack assumes a little-endian machine")
    if dev not in _BYTE_BITS:
        b = torch.arange(256)
        bits = ((b[:, None] >> torch.arange(8)) & 1).to(torch.uint8)     # (256, 8) bit i of byte b
        _BYTE_BITS[dev] = bits.contiguous().view(torch.int64).squeeze(1).to(dev)
    as_bytes = words.contiguous().view(torch.uint8).reshape(-1)          # 4 bytes per word, low byte first
    kernels = _compiled(dev, as_bytes.numel() / 4096 * _UNPACK_GRID_SECONDS)
    if kernels is not None:                                              # the same table, in a compiled loop
        out = torch.empty(as_bytes.numel(), dtype=torch.int64)
        kernels.unpack_into(as_bytes.numpy(), _BYTE_BITS[dev].numpy(), out.numpy())
    else:
        out = torch.index_select(_BYTE_BITS[dev], 0, as_bytes.int())     # (4 * words,) int64 = 8 bools each
    return out.view(torch.bool).reshape(*words.shape, RES)


def pack(grids: torch.Tensor) -> torch.Tensor:
    """bool (..., 32, 32, 32) -> int32 (..., 32, 32), the inverse of :func:`unpack`."""
    weights = torch.ones(RES, dtype=torch.int64, device=grids.device) << torch.arange(RES, device=grids.device)
    words = (grids.long() * weights).sum(-1)                             # 0 .. 2^32-1 in int64
    return torch.where(words >= 2 ** 31, words - 2 ** 32, words).int()  # same bits as int32


_TABLES: dict[torch.device, dict[str, torch.Tensor]] = {}
#: Pseudo primitive tokens after the vocabulary (ids V and V + 1), used by rewriting to find
#: how a program's output depends on one of its primitives: they take six parameters like a
#: primitive, and draw the empty and the full grid whatever the parameters.
EMPTY_PRIMITIVE, FULL_PRIMITIVE = len(token_table()), len(token_table()) + 1


def _tables(device: torch.device) -> dict[str, torch.Tensor]:
    """Per-device lookup tables (built lazily: nothing touches CUDA at import)."""
    if device not in _TABLES:
        table = token_table()
        V = len(table) + 2                           # the vocabulary and the two pseudo primitives
        delta = torch.zeros(V, dtype=torch.long)     # change of the open-argument counter
        code = torch.zeros(V, dtype=torch.long)      # step code of structural tokens
        value = torch.zeros(V, dtype=torch.long)     # integer value of number tokens
        ell = torch.zeros(V, dtype=torch.bool)
        codes = {"union": _UNION, "inter": _INTER, "diff": _DIFF}
        for v, t in enumerate(table.tokens):
            if t.kind == "primitive":
                delta[v], code[v], ell[v] = N_PARAMS - 1, _PRIM, t.name == "ellipsoid"
            elif t.kind == "operator":
                delta[v], code[v] = 1, codes[t.name]
            else:
                delta[v], value[v] = -1, t.params[0]
        fixed = torch.zeros(V, dtype=torch.long)     # 1: draws the empty grid, 2: the full grid
        for v, f in ((EMPTY_PRIMITIVE, 1), (FULL_PRIMITIVE, 2)):
            delta[v], code[v], fixed[v] = N_PARAMS - 1, _PRIM, f
        # with A the top (first operand) and B below it, every operator is
        # (A & (B ^ X)) | (B & Y): union X=Y=-1, intersection X=Y=0, difference X=-1, Y=0
        xy = torch.zeros(_DIFF + 1, 2, dtype=torch.int32)
        xy[_UNION] = torch.tensor([-1, -1], dtype=torch.int32)
        xy[_DIFF] = torch.tensor([-1, 0], dtype=torch.int32)
        _TABLES[device] = {k: x.to(device) for k, x in dict(
            delta=delta, code=code, value=value, ell=ell, xy=xy, fixed=fixed,
            interval=_as_int32(_interval_lut()).reshape(-1),
            column=_as_int32(_column_lut()).reshape(-1)).items()}
    return _TABLES[device]


@functools.cache
def _cpu_tables() -> tuple[np.ndarray, ...]:
    """The CPU tables the compiled per-program path reads, as numpy arrays in its argument order (views of
    :func:`_tables`' tensors, made once)."""
    T = _tables(torch.device("cpu"))
    return tuple(T[k].numpy() for k in ("delta", "code", "value", "ell", "fixed", "interval", "column"))


def _render_cuboids(params: torch.Tensor, T: dict[str, torch.Tensor]) -> torch.Tensor:
    """params (P, 6) long -> int32 (P, 32, 32)."""
    c, d = params[:, :3], params[:, 3:]
    off = torch.arange(RES, device=params.device)[None, None, :] - c[:, :, None]    # (P, 3, 32) p_i - c_i
    inside = 2 * off.abs() <= d[:, :, None]                                          # (P, 3, 32) per axis
    # the z word: |z - c_z| <= d_z/2  <=>  c_z - floor(d_z/2) <= z <= c_z + floor(d_z/2)
    lo = (c[:, 2] - d[:, 2] // 2).clamp(0, RES)
    hi1 = (c[:, 2] + d[:, 2] // 2 + 1).clamp(0, RES)
    word = T["interval"][lo * (RES + 1) + hi1]                                       # (P,)
    in_xy = inside[:, 0, :, None] & inside[:, 1, None, :]                            # (P, 32, 32)
    return torch.where(in_xy, word[:, None, None], torch.zeros((), dtype=torch.int32, device=params.device))


def _render_ellipsoids(params: torch.Tensor, T: dict[str, torch.Tensor]) -> torch.Tensor:
    """params (P, 6) long -> int32 (P, 32, 32)."""
    c, d = params[:, :3], params[:, 3:]
    off = torch.arange(RES, device=params.device)[None, None, :] - c[:, :, None]    # (P, 3, 32)
    d2 = d * d                                                                       # (P, 3)
    D = d2.prod(dim=1)                                                               # (P,) <= 31^6 < 2^31
    w = D[:, None] // d2                                                             # (P, 3) prod of the other d_j^2
    # per-axis terms 4 off^2 D / d_i^2 in int64 (up to 3.6e9); a term above D already puts the
    # column outside, so capping it at D + 1 changes nothing and lets the 2-D part run in int32
    t = torch.minimum(4 * off * off * w[:, :, None], (D + 1)[:, None, None]).int()  # (P, 3, 32)
    R = (D.int()[:, None] - t[:, 0])[:, :, None] - t[:, 1, None, :]                   # (P, 32, 32) >= -2D-2
    q = (4 * w[:, 2]).int()[:, None, None]                                           # 4 dx^2 dy^2 <= 3.7e6
    n = torch.div(R.clamp(min=-1), q, rounding_mode="floor")                          # -1 (outside) .. 240
    base = (c[:, 2] * (_N_MAX + 2) + 1).int()[:, None, None]
    return T["column"][(n + base).reshape(-1)].reshape(n.shape)


def render_primitives(params: torch.Tensor, ellipsoid: torch.Tensor) -> torch.Tensor:
    """Primitives -> packed grids.

    params: (P, 6) long ``x y z dx dy dz`` (centers 0..31, extents >= 1; parts
    outside the grid are clipped); ellipsoid: (P,) bool. Returns int32 (P, 32, 32).
    """
    T = _tables(params.device)
    out = torch.empty(params.shape[0], RES, RES, dtype=torch.int32, device=params.device)
    cub = torch.nonzero(~ellipsoid).flatten()
    ell = torch.nonzero(ellipsoid).flatten()
    if len(cub):
        out[cub] = _render_cuboids(params[cub], T)
    if len(ell):
        out[ell] = _render_ellipsoids(params[ell], T)
    return out


#: on the CPU, programs run one at a time (:meth:`Executor._run_each`), this many per chunk (a chunk's primitive
#: grids are cached together). A search executes most of its programs in batches of 1-8, where the batched
#: path's ~15 tensor operations per stack step cost more than the work; one at a time is also faster on
#: independent sampled programs at every batch size measured (16-2,048: 80-140 us a program, batched 125-400)
EACH_CHUNK = 256
#: most primitive grids kept by the per-program path (4 KiB each): a search renders the same primitives
#: again and again, in the variants of one program
PRIMITIVE_CACHE = 8192


class Executor:
    """Executes padded batches of csg3d token programs."""

    def __init__(self, table: TokenTable | None = None, chunk: int = 1024, per_program: bool = True):
        self.table = table or token_table()
        self.chunk = chunk
        #: on the CPU, run program by program (False: the batched path everywhere); the same bits
        self.per_program = per_program
        self._primitives: dict[tuple[int, ...], np.ndarray] = {}
        self._steps: tuple[list[int], list[int]] | None = None

    def run_packed(self, programs: torch.Tensor, check_degenerate: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """programs (B, L) long -> (words int32 (B, 32, 32), degenerate (B,) bool).

        Each row is a valid program followed by any padding (ignored; negative
        padding is allowed too). ``degenerate`` (only computed with
        ``check_degenerate``) flags programs in which some operator's result is
        empty or equal to one of its operands.
        """
        B = programs.shape[0]
        words = torch.empty(B, RES, RES, dtype=torch.int32, device=programs.device)
        flags = torch.zeros(B, dtype=torch.bool, device=programs.device)
        per_program = self.per_program and programs.device.type == "cpu"
        step = EACH_CHUNK if per_program else self.chunk
        for start in range(0, B, step):
            part = programs[start:start + step]
            out = self._run_each(part, check_degenerate) if per_program else None
            w, f = out if out is not None else self._run(part.clamp(min=0), check_degenerate)
            words[start:start + step] = w
            flags[start:start + step] = f
        return words, flags

    def __getstate__(self) -> dict:
        # a copy sent to another process (a worker pool) starts with an empty primitive cache: up to 32 MiB of
        # grids it would rebuild anyway is not worth pickling
        return {**self.__dict__, "_primitives": {}, "_steps": None}

    def _run_each(self, programs: torch.Tensor, check_degenerate: bool) -> tuple[torch.Tensor, torch.Tensor] | None:
        """:meth:`run_packed` one program at a time in numpy (CPU): the same stack machine on (1024,) int32 words,
        so the same bits, without the batched path's per-step tensor operations; primitives come from a cache of
        rendered grids (the misses rendered together by :func:`render_primitives`). None where a row does not
        end within its length (the batched path defines what such a row gives)."""
        kernels = _compiled(programs.device, len(programs) * _NUMPY_PROGRAM_SECONDS)
        if kernels is not None:
            return self._run_compiled(kernels, programs, check_degenerate)
        if self._steps is None:
            T = _tables(torch.device("cpu"))
            self._steps = (T["delta"].tolist(), T["code"].tolist())
        delta, code = self._steps
        rows = programs.clamp(min=0).tolist()
        parsed: list[list[tuple[int, ...] | int]] = []   # per program: structural steps, primitives as keys
        cache, missing = self._primitives, {}
        if len(cache) >= PRIMITIVE_CACHE:   # (between batches: a batch finds every grid it parsed as cached)
            cache.clear()
        for row in rows:
            steps: list[tuple[int, ...] | int] = []
            need, i, n = 1, 0, len(row)
            while need > 0:
                if i >= n:
                    return None
                tok = row[i]
                need += delta[tok]
                if code[tok] == _PRIM:
                    key = tuple(row[i:i + N_PARAMS + 1])
                    if len(key) <= N_PARAMS:       # parameters cut off by the row's end
                        return None
                    if key not in cache:
                        missing[key] = None
                    steps.append(key)
                elif code[tok] != _NOOP:
                    steps.append(code[tok])
                i += 1
            parsed.append(steps)
        if missing:
            keys = list(missing)
            for key, grid in zip(keys, self._render(torch.tensor(keys, dtype=torch.long))):
                grid.flags.writeable = False                      # shared by every program that draws it
                cache[key] = grid
        out = np.empty((len(rows), _WORDS), dtype=np.int32)
        flags = np.zeros(len(rows), dtype=bool)
        for r, steps in enumerate(parsed):
            stack: list[np.ndarray] = []
            for step in reversed(steps):
                if isinstance(step, tuple):
                    stack.append(cache[step])
                    continue
                a = stack.pop()                                     # the first operand: the top
                b = stack.pop()
                if step == _UNION:
                    res = a | b
                elif step == _INTER:
                    res = a & b
                else:
                    res = a & ~b
                if check_degenerate and not flags[r]:
                    flags[r] = (np.array_equal(res, a) or np.array_equal(res, b) or not res.any())
                stack.append(res)
            out[r] = stack[-1]
        return torch.from_numpy(out).reshape(-1, RES, RES), torch.from_numpy(flags)

    @staticmethod
    def _run_compiled(kernels, programs: torch.Tensor,
                      check_degenerate: bool) -> tuple[torch.Tensor, torch.Tensor] | None:
        """:meth:`_run_each` as one compiled call (plad.domains.csg3d.compiled): the same bits, no primitive cache
        (rendering a primitive there costs about what looking it up costs here)."""
        rows = programs.clamp(min=0).to(torch.int64).contiguous().numpy()
        out = np.empty((len(rows), _WORDS), dtype=np.int32)
        flags = np.zeros(len(rows), dtype=bool)
        status = kernels.run_programs(rows, *_cpu_tables(), check_degenerate, out, flags)
        if status != kernels.DONE:
            return None
        return torch.from_numpy(out).reshape(-1, RES, RES), torch.from_numpy(flags)

    @staticmethod
    def _render(keys: torch.Tensor) -> np.ndarray:
        """keys (K, 7) long: a primitive token and its parameter tokens -> int32 (K, 1024) grids."""
        T = _tables(keys.device)
        grids = render_primitives(T["value"][keys[:, 1:]], T["ell"][keys[:, 0]]).reshape(-1, _WORDS)
        fixed = T["fixed"][keys[:, 0]]
        grids[fixed == 1] = 0
        grids[fixed == 2] = -1
        return grids.numpy()

    def _run(self, programs: torch.Tensor, check_degenerate: bool) -> tuple[torch.Tensor, torch.Tensor]:
        T = _tables(programs.device)
        dev = programs.device
        B, L = programs.shape
        # tokens of the program: those read while the open-argument counter is still positive
        need = 1 + T["delta"][programs].cumsum(dim=1)                     # (B, L) counter after each token
        before = torch.cat([torch.ones(B, 1, dtype=torch.long, device=dev), need[:, :-1]], dim=1)
        valid = (before > 0).long().cumprod(dim=1).bool()                 # (B, L)
        code = torch.where(valid, T["code"][programs], torch.zeros_like(programs))
        # render every primitive of the batch at once; prim p is (rows[p], cols[p]), row-major
        rows, cols = torch.nonzero(code == _PRIM, as_tuple=True)
        idx = (cols[:, None] + torch.arange(1, N_PARAMS + 1, device=dev)).clamp(max=L - 1)
        params = T["value"][programs[rows[:, None], idx]]                 # (P, 6)
        prims = render_primitives(params, T["ell"][programs[rows, cols]]).reshape(-1, _WORDS)
        fixed = T["fixed"][programs[rows, cols]]
        if bool((fixed > 0).any()):
            prims[fixed == 1] = 0
            prims[fixed == 2] = -1
        # structural tokens right to left: step s of a row is its s-th structural token from the end.
        # Rows are sorted by step count, longest first, so the rows still running at step s are a
        # prefix of the batch and each step only touches those.
        structural = code != _NOOP
        n_steps = structural.sum(1)                                       # (B,)
        order = torch.argsort(n_steps, descending=True, stable=True)
        rank = structural.flip(1).long().cumsum(1).flip(1) - 1            # (B, L) index from the end
        S = int(n_steps.max()) if B else 0
        steps = torch.zeros(B, S + 1, dtype=torch.long, device=dev)       # column S: scratch for the rest
        prim_of = torch.zeros(B, S + 1, dtype=torch.long, device=dev)
        col = torch.where(structural, rank, torch.full_like(rank, S))
        steps.scatter_(1, col, code)
        prim_id = torch.zeros_like(programs)
        prim_id[rows, cols] = torch.arange(len(rows), device=dev)
        prim_of.scatter_(1, col, torch.where(code == _PRIM, prim_id, torch.zeros_like(prim_id)))
        steps, prim_of = steps[order], prim_of[order]
        running = n_steps[order].tolist()
        # The top of each stack lives apart in ``top`` and ``stack`` holds the entries below it, so a
        # step reads one stack entry (an operator's second operand) and writes at most one (a
        # primitive pushes the old top down). There are fewer entries below the top than the
        # program has primitives; slot ``depth_max`` is scratch for rows with nothing to store.
        depth_max = int((code == _PRIM).sum(1).max()) if B else 0
        stack = torch.empty(B, depth_max + 1, _WORDS, dtype=torch.int32, device=dev)
        top = torch.zeros(B, _WORDS, dtype=torch.int32, device=dev)
        below = torch.zeros(B, dtype=torch.long, device=dev)              # entries under the top
        degenerate = torch.zeros(B, dtype=torch.bool, device=dev)
        ar = torch.arange(B, device=dev)
        n = B
        for s in range(S):
            while running[n - 1] <= s:                                    # rows that have finished
                n -= 1
            c, bd, r, a = steps[:n, s], below[:n], ar[:n], top[:n]        # a (n, 1024): first operand
            is_prim, is_op = c == _PRIM, c >= _UNION
            if s > 0:                                                     # (the first step has no top yet)
                stack[r, torch.where(is_prim, bd, torch.full_like(bd, depth_max))] = a
            b = stack[r, (bd - 1).clamp(min=0)]                           # (n, 1024) second operand
            xy = T["xy"][c]                                               # (n, 2)
            res = (a & (b ^ xy[:, :1])) | (b & xy[:, 1:])
            if check_degenerate:
                same = (res == a).all(1) | (res == b).all(1) | (res == 0).all(1)
                degenerate[:n] |= is_op & same
            top[:n] = torch.where(is_prim[:, None], prims[prim_of[:n, s]], res) if len(rows) else res
            below[:n] = bd + (is_prim & (s > 0)).long() - is_op.long()
        words = torch.empty(B, _WORDS, dtype=torch.int32, device=dev)
        words[order] = top
        flags = torch.empty(B, dtype=torch.bool, device=dev)
        flags[order] = degenerate
        return words.reshape(B, RES, RES), flags

    def __call__(self, programs: torch.Tensor) -> torch.Tensor:
        """programs (B, L) long -> bool (B, 32, 32, 32) indexed [x, y, z]."""
        return unpack(self.run_packed(programs)[0])
