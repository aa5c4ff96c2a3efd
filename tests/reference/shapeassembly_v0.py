"""The ShapeAssembly executor and voxelizer as they were before they were made fast (frozen copy, commit 0d8ec49).

``plad/data/datasets/partnet/execute.py`` (the executor), ``voxels.py``'s ``voxelize_batch`` and
``plad/domains/shapeassembly/tokens.py``'s ``to_statements`` / ``cuboids.py``'s ``token_cuboids``, copied
unchanged but for the imports. The tests assert that the fast versions give bit-identical cuboids, grids and
unique counts (``np.array_equal``), and ``bench/shapeassembly_exec.py`` times them as the baseline. Do not
"improve" this file: it is the definition of the outputs the fast code must reproduce.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np
import torch

from plad.data.datasets.partnet.execute import ExecutionError
from plad.data.datasets.partnet.lang import FACES, Block, Program, Stmt
from plad.domains.grammar import ProgramError
from plad.domains.shapeassembly.tokens import RES, token_table

MIN_HALF = 0.55 / RES
TOL = 1e-6


F32 = np.float32
_EYE = np.eye(3, dtype=F32)
_HALF = F32(0.5)
# sample lattice of the grow step: (i/9, j/9, k/9) with x fastest, then y, then z; (1000, 3)
_STEPS = np.arange(10, dtype=F32) / F32(9)
_K, _J, _I = np.meshgrid(_STEPS, _STEPS, _STEPS, indexing="ij")
_LATTICE = np.stack([_I, _J, _K], axis=-1).reshape(-1, 3)   # row i + 10 j + 100 k = (i, j, k) / 9
# corners as local coordinates (8, 3)
_CORNERS = np.array([[x, y, z] for x in (1, 0) for y in (1, 0) for z in (1, 0)], dtype=F32)
# bracketing candidate offsets (8, 3) for the nearest-lattice search
_BRACKET = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)], dtype=np.int64)
SMALL_EPS = F32(1e-4)
EPS = F32(0.01)


class Cuboid:
    """State of one cuboid in its block's frame.

    pos (3,), axes (3, 3) float32 with rows u_x, u_y, u_z, dims (3,).
    ``records``: attachment records [(local point q (3,), world point g (3,))];
    ``moves``: move records [(q (3,), target name)].
    """

    __slots__ = ("name", "pos", "axes", "dims", "aligned", "records", "moves", "parent", "parent_axis", "is_sub")

    def __init__(self, name: str, dims, aligned: bool, is_sub: bool = False):
        self.name = name
        self.pos = np.zeros(3, dtype=F32)
        self.axes = _EYE.copy()
        self.dims = np.asarray(dims, dtype=F32).copy()
        self.aligned = aligned
        self.records: list[tuple[np.ndarray, np.ndarray]] = []
        self.moves: list[tuple[np.ndarray, str]] = []
        self.parent: str | None = None
        self.parent_axis: int | None = None
        self.is_sub = is_sub

    def world(self, q: np.ndarray) -> np.ndarray:
        """Local point(s) q (..., 3) in [0,1]^3 -> world (..., 3)."""
        return ((q - _HALF) * self.dims) @ self.axes + self.pos

    def rel(self, g: np.ndarray) -> np.ndarray:
        """World point(s) g (3,) or (n, 3) -> local coordinates, unclamped (float32 LAPACK solve)."""
        origin = self.world(np.zeros(3, dtype=F32))
        a = (self.axes * self.dims[:, None]).T            # columns d_a u_a
        rhs = (g - origin).T
        return np.linalg.solve(a, rhs).T.astype(F32, copy=False)

    def change(self, q: np.ndarray, a: int) -> np.ndarray:
        """How world(q) moves per unit increase of dims[a] (the change vector of docs/shapeassembly.md)."""
        return (q[a] - _HALF) * self.axes[a]

    def corners(self) -> np.ndarray:
        return self.world(_CORNERS)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross has ~10x the call overhead)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]],
                    dtype=a.dtype)


def _norm(v: np.ndarray) -> F32:
    return F32(math.sqrt(float(np.dot(v, v))))


def _rotation(angle: F32, n: np.ndarray) -> np.ndarray:
    """Rotation matrix by ``angle`` about unit axis ``n`` (3, 3) float32."""
    s, c = F32(np.sin(angle)), F32(np.cos(angle))
    t = F32(1) - c
    x, y, z = n
    return np.array([[c + t * x * x, t * x * y - s * z, t * x * z + s * y],
                     [t * x * y + s * z, c + t * y * y, t * y * z - s * x],
                     [t * x * z - s * y, t * y * z + s * x, c + t * z * z]], dtype=F32)


def _min_rotation(cur: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Minimal rotation taking direction ``cur`` to ``target`` (docs/shapeassembly.md, "Second attach", step 4)."""
    ncur = cur / _norm(cur)
    ntar = target / _norm(target)
    normal = _cross(ncur, ntar)
    nn = _norm(normal)
    if nn == 0:
        # the original's degenerate branch: rotate by pi about a (non-perpendicular) axis
        n0, n1, n2 = ncur
        t = np.array([n0, -n2, n1] if n0 != 0 else [n2, n1, -n0] if n1 != 0 else [-n1, n0, n2], dtype=F32)
        return _rotation(F32(math.pi), t / _norm(t))
    with np.errstate(invalid="ignore"):
        angle = F32(np.arccos(F32(np.dot(ncur, ntar))))
    if angle == 0 or np.isnan(angle):
        return _EYE
    return _rotation(angle, normal / nn)


def _frame(c: Cuboid) -> np.ndarray:
    """The grow step's sampling frame (3, 3) rows: normalized u_x, u_y and their cross product."""
    x = c.axes[0] / (_norm(c.axes[0]) + F32(1e-8))
    y = c.axes[1] / (_norm(c.axes[1]) + F32(1e-8))
    return np.stack([x, y, _cross(x, y)])


def _samples(c: Cuboid, frame: np.ndarray) -> np.ndarray:
    """(1000, 3) lattice samples of a cuboid in world space."""
    return ((_LATTICE - _HALF) * c.dims) @ frame + c.pos


def _nearest_pair(a: Cuboid, b: Cuboid) -> tuple[np.ndarray, np.ndarray]:
    """Closest pair (sample of a, sample of b) with the brute-force search's tie rules."""
    fa, fb = _frame(a), _frame(b)
    sa, sb = _samples(a, fa), _samples(b, fb)                  # (1000, 3) each
    db = b.dims
    if not np.all(db > 0) or abs(float(np.linalg.det(fb)) - 1.0) > 1e-3:
        # not a proper lattice in an orthonormal frame: brute force (1000 x 1000)
        d2 = ((sa[:, None, :] - sb[None, :, :]) ** 2).sum(-1)
        nearest = d2.argmin(1)
        best = d2[np.arange(len(sa)), nearest]
    else:
        # coordinates of a's samples in b's lattice units; bracketing indices per axis
        t = (sa - b.pos) @ fb.T                                 # (1000, 3)
        u = (t / db + 0.5) * 9.0
        lo = np.clip(np.floor(u).astype(np.int64), 0, 9)
        idx = np.minimum(lo[:, None, :] + _BRACKET[None], 9)    # (1000, 8, 3)
        flat = idx[..., 0] + 10 * idx[..., 1] + 100 * idx[..., 2]  # (1000, 8)
        d2 = ((sa[:, None, :] - sb[flat]) ** 2).sum(-1)         # (1000, 8)
        m = d2.min(1)
        # first index among equal distances, as the exhaustive search returns it
        nearest = np.where(d2 == m[:, None], flat, 1000).min(1)
        best = m
    i = int(best.argmin())
    return sa[i], sb[nearest[i]]


def nearest_pair_brute(a: Cuboid, b: Cuboid) -> tuple[np.ndarray, np.ndarray]:
    """The original's exhaustive search: all 1000 x 1000 sample distances (reference, slow)."""
    sa, sb = _samples(a, _frame(a)), _samples(b, _frame(b))
    d2 = ((sa[:, None, :] - sb[None, :, :]) ** 2).sum(-1)                 # (1000, 1000)
    nearest = d2.argmin(1)
    i = int(d2[np.arange(len(sa)), nearest].argmin())
    return sa[i], sb[nearest[i]]


class BlockState:
    """Executes the statements of one block in its local frame.

    ``nearest`` is the grow step's closest-sample search (default: the exact
    8-candidate search; :func:`nearest_pair_brute` gives the original's).
    """

    def __init__(self, bbox_dims, bbox_aligned: bool = True, copy_names=None, nearest=None):
        self.cuboids: dict[str, Cuboid] = {"bbox": Cuboid("bbox", bbox_dims, bbox_aligned)}
        self.nearest = nearest or _nearest_pair
        # copy naming: the full language counts cuboids ("cube{N}"); the
        # discretized variant names copies after their parent
        self.copy_names = copy_names

    def run(self, stmts: list[Stmt]) -> None:
        for s in stmts:
            try:
                getattr(self, "_" + s.op)(*s.args)
            except np.linalg.LinAlgError as err:
                raise ExecutionError(s.line, f"{s.op} cannot be executed: a cuboid has a singular frame ({err})") \
                    from None

    # ---- statements --------------------------------------------------------------
    def _cuboid(self, name: str, dims, aligned: bool, is_sub: bool) -> None:
        if name in self.cuboids:
            self.cuboids[name].dims = np.asarray(dims, dtype=F32).copy()
        else:
            self.cuboids[name] = Cuboid(name, dims, aligned, is_sub)

    def _attach(self, a_name: str, b_name: str, q1, q2) -> None:
        a, b = self.cuboids[a_name], self.cuboids[b_name]
        q1 = np.asarray(q1, dtype=F32)
        q2 = np.asarray(q2, dtype=F32)
        g = b.world(q2)
        b.records.append((q2, g))
        k = len(a.records)
        if k == 0:
            a.pos = a.pos + (g - a.world(q1))
        elif a.aligned:
            self._grow(a, b)
        elif k == 1:
            self._second(a, q1, g, *a.records[0])
        else:
            self._general(a, q1, g)
        a.records.append((q1, g))
        a.moves.append((q1, b_name))

    def _grow(self, a: Cuboid, b: Cuboid) -> None:
        """Aligned mover with records: push the side facing b across the gap (docs/shapeassembly.md, "Grow")."""
        for inner, outer in ((b, a), (a, b)):
            r = inner.rel(outer.corners())                       # (8, 3)
            if np.any((r.min(1) >= 0) & (r.max(1) <= 1)):
                return
        p, c = self.nearest(a, b)
        mv = max(float(a.dims.max()), float(b.dims.max()))
        if _norm(p - c) < mv * 0.05:
            return
        r = np.clip(a.rel(p), 0, 1).astype(F32)
        opposite = F32(1) - r
        anchor = a.world(opposite)
        grow = np.zeros(3, dtype=F32)
        for ax in range(3):
            k = (r[ax] - _HALF) * a.axes[ax][ax]
            if k != 0:
                d = (c[ax] - p[ax]) / (F32(2) * k)
                if d > 0:
                    grow[ax] = d
        a.dims = a.dims + grow
        a.pos = a.pos + (anchor - a.world(opposite))

    def _second(self, a: Cuboid, q1: np.ndarray, g: np.ndarray, qp: np.ndarray, gp: np.ndarray) -> None:
        """Unaligned mover with one record: scale one dimension, then swing about the record ("Second attach")."""
        b = a.world(q1)
        if _norm(b - g) < SMALL_EPS:
            return
        dist = _norm(g - gp)
        e = b - gp
        best_s, best_axis = None, -1
        with np.errstate(invalid="ignore"):
            for ax in (1, 2, 0):                                  # height, width, length
                n, m = a.change(q1, ax), a.change(qp, ax)
                if np.abs(n).sum() + np.abs(m).sum() < SMALL_EPS:
                    continue
                s, disc = self._quadratic(n - m, e, dist)
                if disc > 0 and abs(s) < (abs(best_s) if best_s is not None else F32(1e8)):
                    best_s, best_axis = s, ax
            if best_s is None:
                n = a.change(q1, 1) + a.change(q1, 0) + a.change(q1, 2)
                m = a.change(qp, 1) + a.change(qp, 0) + a.change(qp, 2)
                s, disc = self._quadratic(n - m, e, dist)
                if not np.isnan(s) and disc > 0:
                    a.dims = a.dims + s
            else:
                a.dims[best_axis] += best_s
        a.pos = a.pos + (gp - a.world(qp))
        nb = a.world(q1) - gp
        nc = g - gp
        if _norm(nb) == 0 or _norm(nc) == 0 or _norm(nb - nc) < SMALL_EPS:
            return
        rot = _min_rotation(nb, nc)
        a.axes = (a.axes @ rot.T).astype(F32)
        a.pos = a.pos + (gp - a.world(qp))

    @staticmethod
    def _quadratic(f: np.ndarray, e: np.ndarray, dist: F32) -> tuple[F32, F32]:
        """Positive root s of |e + s f| = dist, and the discriminant."""
        a2 = F32((f * f).sum())
        b2 = F32(2) * F32((e * f).sum())
        c2 = F32((e * e).sum()) - dist * dist
        disc = b2 * b2 - F32(4) * a2 * c2
        return (-b2 + F32(np.sqrt(disc))) / (F32(2) * a2 + F32(1e-8)), disc

    def _general(self, a: Cuboid, q1: np.ndarray, g: np.ndarray) -> None:
        """Unaligned mover with two or more records: orient if colinear, then maybe scale ("General attach")."""
        recs = a.records
        colinear = len(recs) == 2 or all(
            _norm(_cross(recs[i][1] - recs[0][1], recs[1][1] - recs[0][1])) <= EPS for i in range(2, len(recs)))
        if colinear:
            self._orient(a, q1, g)
        self._scale(a, q1, g)

    def _orient(self, a: Cuboid, q1: np.ndarray, g: np.ndarray) -> None:
        (q0, g0), (_, g1) = a.records[0], a.records[1]
        w = (g0 - g1) / (_norm(g0 - g1) + F32(1e-8))
        b = a.world(q1)
        ww = F32(np.dot(w, w)) + F32(1e-8)
        gp = g + ((np.dot(w, b) - np.dot(w, g)) / ww) * w
        ap = g0 + ((np.dot(w, b) - np.dot(w, g0)) / ww) * w
        f, h = b - ap, gp - ap
        ff = F32(np.dot(f, f))
        with np.errstate(invalid="ignore"):
            disc = (F32(2) * ff) ** 2 - F32(4) * ff * (ff - F32(np.dot(h, h)))
            s = (-F32(2) * ff + F32(np.sqrt(disc))) / (F32(2) * ff + F32(1e-8))
        if np.isnan(s):
            return
        o = f * (F32(1) + s)
        if _norm(o) == 0 or _norm(h) == 0 or _norm(o - h) < EPS:
            return
        no, nh = o / (_norm(o) + F32(1e-8)), h / (_norm(h) + F32(1e-8))
        with np.errstate(invalid="ignore"):
            theta = F32(np.arccos(F32(np.dot(no, nh))))
        rot = _rotation(theta, w)
        if _norm(rot @ no - nh) > EPS:
            rot = _rotation(theta, -w)
        a.axes = (a.axes @ rot.T).astype(F32)
        a.pos = a.pos + (g0 - a.world(q0))

    def _scale(self, a: Cuboid, q1: np.ndarray, g: np.ndarray) -> None:
        b = a.world(q1)
        t = g - b
        if _norm(t) < EPS:
            return
        q0, g0 = a.records[0]
        nt = t / (_norm(t) + F32(1e-8))
        chosen = -1
        for ax in (1, 2, 0):
            v0 = a.change(q0, ax)
            if any(_norm(v0 - a.change(q, ax)) > EPS for q, _ in a.records):
                continue
            v = a.change(q1, ax)
            nv = v / (_norm(v) + F32(1e-8))
            if np.dot(nt, nv) > F32(0.9):
                chosen = ax                     # the original keeps the last passing axis
        if chosen < 0:
            return
        v = a.change(q1, chosen)
        nn = v / (_norm(v) + F32(1e-8))
        tt = (np.dot(nn, b) - np.dot(nn, g)) / (F32(np.dot(nn, nn)) + F32(1e-8))
        a.dims[chosen] += abs(tt) * _norm(nn) / (_norm(v - a.change(q0, chosen)) + F32(1e-8))
        a.pos = a.pos + (g0 - a.world(q0))

    def _squeeze(self, a_name: str, b_name: str, c_name: str, face: str, u: float, v: float) -> None:
        axis = FACES.index(face) // 2
        side = 1.0 if face in ("right", "top", "front") else 0.0
        others = [i for i in range(3) if i != axis]

        def points(side_a: float, target_side: float) -> tuple[list[float], list[float]]:
            qa = [0.5, 0.5, 0.5]
            qa[axis] = side_a
            qt = [0.0, 0.0, 0.0]
            qt[axis] = target_side
            qt[others[0]], qt[others[1]] = u, v
            return qa, qt

        q1, q2 = points(side, side if b_name == "bbox" else 1 - side)
        self._attach(a_name, b_name, q1, q2)
        q1, q2 = points(1 - side, 1 - side if c_name == "bbox" else side)
        self._attach(a_name, c_name, q1, q2)

    def _new_copy(self, a: Cuboid, axis: int | None, index: int | None) -> str:
        if self.copy_names is None:
            name = f"cube{len(self.cuboids) - 1}"
        else:
            name = self.copy_names(a.name, index)
        self._cuboid(name, a.dims, a.aligned, False)
        copy = self.cuboids[name]
        copy.parent, copy.parent_axis = a.name, axis
        return name

    def _reflect(self, a_name: str, axis: int) -> None:
        a = self.cuboids[a_name]
        name = self._new_copy(a, axis, None)
        for q, t_name in list(a.moves):
            qr = q.copy()
            qr[axis] = F32(1) - q[axis]
            w = a.world(q)
            w[axis] = -w[axis]                   # mirror through the bbox center (the origin)
            target = self.cuboids[t_name]
            self._attach(name, t_name, qr, np.clip(target.rel(w), 0, 1).astype(F32))

    def _translate(self, a_name: str, axis: int, n: int, d: float) -> None:
        a = self.cuboids[a_name]
        bbox = self.cuboids["bbox"]
        step = bbox.dims[axis] * F32(d) / F32(n)
        direction = bbox.axes[axis]
        for i in range(1, n + 1):
            name = self._new_copy(a, None, i)
            for q, t_name in list(a.moves):
                w = a.world(q) + direction * step * F32(i)
                target = self.cuboids[t_name]
                self._attach(name, t_name, q, np.clip(target.rel(w), 0, 1).astype(F32))


def _place(c: Cuboid, p_pos, p_axes, scale) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map a cuboid from its block frame into the placement's frame (docs/shapeassembly.md, "Sub-assemblies")."""
    return c.pos @ p_axes + p_pos, (c.axes @ p_axes).astype(F32), (c.dims * scale).astype(F32)


def execute_program(program: Program, copy_names=None, nearest=None) -> np.ndarray:
    """Run a parsed program; returns the leaf cuboids (n, 15) float32 in output order.

    Columns: center xyz, x-axis xyz, y-axis xyz, z-axis xyz, dims (l, h, w).
    ``copy_names(parent, i)`` names reflect (i None) and translate copies; by
    default the full language's ``cube{N}``. ``nearest``: see :class:`BlockState`.
    """
    root = program.blocks[program.root]
    root_dims = np.asarray(root.bbox_dims, dtype=F32)
    # queue of (block name, placement (pos, axes, dims), flip axis or None)
    queue = deque([(program.root, (np.zeros(3, dtype=F32), _EYE, root_dims), None)])
    leaves: list[np.ndarray] = []
    while queue:
        name, (p_pos, p_axes, p_dims), flip = queue.popleft()
        block = program.blocks[name]
        state = BlockState(block.bbox_dims, block.stmts[0].args[2], copy_names, nearest)
        state.run(block.stmts)
        cuboids = state.cuboids
        scale = (p_dims / cuboids["bbox"].dims).astype(F32)
        for c in list(cuboids.values())[1:]:
            pos, axes = c.pos, c.axes
            if flip is not None:
                # rotate the block's content by 180 degrees about the flip axis
                pos = pos.copy()
                pos[flip] = -pos[flip]
                axes = -axes
                axes[:, flip] = -axes[:, flip]
            c.pos, c.axes = pos, axes
            placed = _place(c, p_pos, p_axes, scale)
            if c.is_sub:
                queue.append((c.name, placed, None))
            elif c.parent is not None and cuboids[c.parent].is_sub:
                queue.append((c.parent, placed, c.parent_axis))
            else:
                leaves.append(np.concatenate([placed[0], placed[1].reshape(-1), placed[2]]))
    if not leaves:
        return np.zeros((0, 15), dtype=F32)
    return np.stack(leaves).astype(F32)


def voxelize_batch(cuboids: torch.Tensor, owner: torch.Tensor, batch: int, min_half: float = MIN_HALF,
                   res: int = RES) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxelize cuboids of many shapes at once.

    cuboids: (N, 15) float (center, three axes, dims) already in the unit-cube frame;
    owner: (N,) long, the shape each cuboid belongs to (0 <= owner < batch).
    Returns (grids (batch, res, res, res) bool indexed [x, y, z], unique (N,) long:
    voxels of each cuboid that no other cuboid of its shape occupies).
    """
    c = cuboids.detach().cpu().numpy().astype(np.float64)
    own = owner.detach().cpu().numpy()
    n = len(c)
    p = c[:, 0:3]
    u = c[:, 3:12].reshape(n, 3, 3)
    u = u / np.linalg.norm(u, axis=2, keepdims=True)                      # (N, 3 axes, 3)
    half = np.maximum(np.abs(c[:, 12:15]) / 2, min_half) + TOL             # (N, 3)
    # axis-aligned extent of each cuboid -> inclusive voxel index ranges per axis
    ext = (half[:, :, None] * np.abs(u)).sum(1)                            # (N, 3)
    lo = np.clip(np.ceil((p - ext + 0.5) * res - 0.5), 0, res).astype(np.int64)
    hi = np.clip(np.floor((p + ext + 0.5) * res - 0.5), -1, res - 1).astype(np.int64)
    centers = (np.arange(res) + 0.5) / res - 0.5                           # (res,) voxel centers per axis
    count = np.zeros((batch, res, res, res), dtype=np.int16)
    boxes = []
    for m in range(n):
        (x0, y0, z0), (x1, y1, z1) = lo[m], hi[m] + 1
        if x1 <= x0 or y1 <= y0 or z1 <= z0:
            boxes.append(None)
            continue
        # (c - p) per axis over the box, then the three projections by broadcasting:
        # proj_a[i, j, k] = dx[i] u_a,x + dy[j] u_a,y + dz[k] u_a,z   (box shape)
        d = [centers[x0:x1] - p[m, 0], centers[y0:y1] - p[m, 1], centers[z0:z1] - p[m, 2]]
        if np.count_nonzero(u[m]) == 3:
            # axes along the grid axes (the common case): the test separates into three
            # 1-D tests; the zero terms of the general sum are exact, so this is the same test
            k = np.abs(u[m]).argmax(1)                                     # grid axis of each cuboid axis
            ok = [None, None, None]
            for a in range(3):
                ok[k[a]] = np.abs(d[k[a]] * u[m, a, k[a]]) <= half[m, a]
            inside = ok[0][:, None, None] & ok[1][None, :, None] & ok[2][None, None, :]
        else:
            dx, dy, dz = d[0][:, None, None], d[1][None, :, None], d[2][None, None, :]
            inside = None
            for a in range(3):
                ua = u[m, a]
                proj = dx * ua[0] + dy * ua[1] + dz * ua[2]
                ok_a = np.abs(proj) <= half[m, a]
                inside = ok_a if inside is None else inside & ok_a
        count[own[m], x0:x1, y0:y1, z0:z1] += inside
        boxes.append(inside)
    # voxels covered exactly once in their shape belong uniquely to their cuboid
    unique = np.zeros(n, dtype=np.int64)
    for m, inside in enumerate(boxes):
        if inside is not None:
            (x0, y0, z0), (x1, y1, z1) = lo[m], hi[m] + 1
            unique[m] = int((inside & (count[own[m], x0:x1, y0:y1, z0:z1] == 1)).sum())
    return torch.from_numpy(count > 0), torch.from_numpy(unique)


def _cind(j: int) -> str:
    return "bbox" if j < 0 else f"cube{j}"


def attach_points(face: str, to_bbox: bool, mover_uv: tuple[float, float],
                  target_uv: tuple[float, float]) -> tuple[list[float], list[float]]:
    """Local points (mover q1, target q2) of ``Attach cind face fpos fpos`` (docs/shapeassembly.md).

    The mover's coordinate on the face axis is 1 for right/top/front and 0
    otherwise; the target uses the opposite side, except the bbox with top/bot
    (same side, from inside). The fpos give the two remaining coordinates in
    increasing axis order.
    """
    axis = FACES.index(face) // 2
    side = 1.0 if face in ("right", "top", "front") else 0.0
    other = side if (to_bbox and face in ("top", "bot")) else 1.0 - side
    q1, q2 = [0.0] * 3, [0.0] * 3
    q1[axis], q2[axis] = side, other
    rest = [a for a in range(3) if a != axis]
    for a, x, y in zip(rest, mover_uv, target_uv):
        q1[a], q2[a] = x, y
    return q1, q2


def to_statements(ids: Sequence[int]) -> list[Stmt]:
    """Token ids of a valid program -> statements of the equivalent one-block program."""
    table = token_table()
    toks = [table.tokens[int(i)] for i in ids]
    stmts: list[Stmt] = []
    pos, count = 0, 0

    def args(n: int) -> list:
        nonlocal pos
        out = [toks[pos + 1 + k].params for k in range(n)]
        pos += 1 + n
        return out

    while pos < len(toks):
        kind = toks[pos].kind
        mover = f"cube{count - 1}"
        if kind == "start":
            (h,), = args(1)
            stmts.append(Stmt("cuboid", ("bbox", (1.0, h / RES, 1.0), False, False)))
        elif kind == "cuboid":
            dims = tuple(p[0] / RES for p in args(3))
            stmts.append(Stmt("cuboid", (f"cube{count}", dims, False, False)))
            count += 1
        elif kind == "attach":
            (j,), (face,), uv1, uv2 = args(4)
            q1, q2 = attach_points(face, j < 0, (uv1[0] / 10, uv1[1] / 10), (uv2[0] / 10, uv2[1] / 10))
            stmts.append(Stmt("attach", (mover, _cind(j), tuple(q1), tuple(q2))))
        elif kind == "squeeze":
            (j1,), (j2,), (face,), uv = args(4)
            stmts.append(Stmt("squeeze", (mover, _cind(j1), _cind(j2), face, uv[0] / 10, uv[1] / 10)))
        elif kind == "reflect":
            (axis,), = args(1)
            stmts.append(Stmt("reflect", (mover, axis)))
        elif kind == "translate":
            (axis,), (n,), (d,) = args(3)
            stmts.append(Stmt("translate", (mover, axis, n, d / RES)))
        elif kind == "end":
            break
        else:
            raise ProgramError(f"token {pos} {toks[pos].name!r} cannot start a statement", position=pos)
    return stmts


def _copy_name(parent: str, index: int | None) -> str:
    return f"{parent}_ref" if index is None else f"{parent}_trans_{index}"


def token_cuboids(ids: Sequence[int]) -> np.ndarray:
    """Cuboids (n, 15) float32 of a valid token program (copies included), in the bbox frame."""
    program = Program({"Program_0": Block("Program_0", to_statements(ids))}, "Program_0")
    return execute_program(program, copy_names=_copy_name)


def run_batch(rows) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``ShapeAssembly.run_batch`` on these functions: grids, unique, owner, ok."""
    cubs, owners, ok = [], [], []
    for b, ids in enumerate(rows):
        try:
            c = token_cuboids(ids)
            ok.append(True)
        except ExecutionError:
            c = np.zeros((0, 15), np.float32)
            ok.append(False)
        cubs.append(c)
        owners.append(np.full(len(c), b, dtype=np.int64))
    cuboids = torch.from_numpy(np.concatenate(cubs) if cubs else np.zeros((0, 15), np.float32))
    owner = torch.from_numpy(np.concatenate(owners) if owners else np.zeros(0, np.int64))
    grids, unique = voxelize_batch(cuboids, owner, len(rows))
    return grids, unique, owner, torch.tensor(ok, dtype=torch.bool)
