"""ShapeAssembly's rewriting moves (:class:`plad.domains.space.RewriteSpace`).

What the discretized grammar allows (``START h (Cuboid l h w MOVES [SYM])+ END``):

* PO blocks: the bbox height (``START h``), then one block per part, in
  token order: its dimensions and every argument of its moves and symmetry.
  Numbers move by +-1, +-2 (``wide``: also +-4, +-8) within 1..31; an in-face
  point ``fpos_i_j`` moves one grid step in i or j (``wide``: also two steps
  and diagonally); a reflect/translate axis and a copy count may take any
  other value; with ``wide`` also a face, and a reference any other cuboid
  the part may attach to (the bbox or an earlier cuboid).
* No expression tree: parts are not boolean operands, so there is no pruning.
  Removal instead (:meth:`ShapeAssemblyRewrite.removals`): a part that no
  later part attaches to may go, the later parts' references renumbered
  (``cube j`` -> ``cube j-1`` past it); what a network's misplaced part needs,
  since insertion only adds voxels.
* Insertion, from the residual (target voxels the program misses; the
  language has no difference): for each of the largest missed components, a
  part whose dimensions are those of a box grown inside it (three boxes from
  three seeds: the deepest voxel, then the deepest ones the earlier boxes
  leave uncovered) (:func:`plad.domains.boxes.residual_boxes`),
  attached by one ``Attach`` to the bbox or to a declared cuboid. For every
  (cuboid, face) the in-face points that bring the part's center closest to
  the box's center are found in closed form over the 9 x 9 x 9 x 9 grid (a
  first attach only translates the part: center = target point - mover
  offset); the closest placements are proposed, each also followed by
  ``Reflect X`` and ``Reflect Z`` (left/right and front/back symmetry). From
  the empty program the bbox height comes from the target's vertical extent.
* No screen: execution (a Python interpreter, ~2 ms a program) dominates,
  and every candidate is scored exactly.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from plad.data.datasets.partnet.execute import BlockState, ExecutionError
from plad.domains.boxes import residual_boxes
from plad.domains.shapeassembly.tokens import FACE_TOKENS, FPOS, MAX_CUBOIDS, RES, attach_points, to_statements
from plad.domains.space import Candidates, RewriteSpace, Slot

LOCAL_STEPS = (-2, -1, 1, 2)
WIDE_STEPS = (-8, -4, -2, -1, 1, 2, 4, 8)
LOCAL_FPOS = ((-1, 0), (1, 0), (0, -1), (0, 1))
WIDE_FPOS = tuple((di, dj) for di in range(-2, 3) for dj in range(-2, 3) if (di, dj) != (0, 0))
#: missed-voxel components proposed per insertion, boxes grown in each, and placements per box
COMPONENTS = 2
GROWN = 3
PLACEMENTS = 2
_GRID = np.array(list(FPOS), dtype=np.float64) / 10.0
_FACE_AXIS = {"left": 0, "right": 0, "bot": 1, "top": 1, "back": 2, "front": 2}
#: (axis, indices into FACE_TOKENS of the faces across it)
_FACES_BY_AXIS = tuple((a, tuple(i for i, f in enumerate(FACE_TOKENS) if _FACE_AXIS[f] == a)) for a in range(3))


class ShapeAssemblyRewrite(RewriteSpace):
    screen_keep = None
    search_defaults = {"insertions": MAX_CUBOIDS, "tune_sweeps": 4,
                       "refine": {"rounds": 1, "po_sweeps": 2, "wide": False, "insert": False}}
    # effort levels (measured in docs/inference.md): fast skips the refinement; default is the greedy search
    # above; best a beam of 4 over partial programs, its 2 best finds refined (the beam's lookahead pays, more
    # polishing of the greedy program does not). The default stays greedy: the search-seeded fine-tuning seeds
    # with it, and the committed column was trained on its programs
    search_efforts = {**RewriteSpace.search_efforts, "best": {"beam_width": 4, "beam_refine": 2}}
    # a network's program holds misplaced parts, which insertion (it only adds voxels) cannot undo: removal
    # after each round's PO scores better in less time (docs/inference.md)
    refine_defaults = {"remove": True}

    def __init__(self, domain):
        super().__init__(domain)
        table = domain.tokens
        self.table = table
        self.kind = [t.kind for t in table.tokens]
        self.params = [t.params for t in table.tokens]
        self.id = {t.name: i for i, t in enumerate(table.tokens)}

    # ---- PO -------------------------------------------------------------------------------
    def _num(self, v: int, wide: bool) -> tuple[int, ...]:
        return tuple(self.id[str(v + s)] for s in (WIDE_STEPS if wide else LOCAL_STEPS) if 1 <= v + s <= RES - 1)

    def _fpos(self, i: int, j: int, wide: bool) -> tuple[int, ...]:
        return tuple(self.id[f"fpos_{i + a}_{j + b}"] for a, b in (WIDE_FPOS if wide else LOCAL_FPOS)
                     if i + a in FPOS and j + b in FPOS)

    def _slot(self, pos: int, token: int, mover: int, wide: bool) -> Slot | None:
        kind, params = self.kind[token], self.params[token]
        if kind == "num":
            choices = self._num(params[0], wide)
        elif kind == "fpos":
            choices = self._fpos(params[0], params[1], wide)
        elif kind in ("axis", "snum"):
            choices = tuple(i for i, k in enumerate(self.kind) if k == kind and i != token)
        elif kind == "face" and wide:
            choices = tuple(self.id[f] for f in FACE_TOKENS if self.id[f] != token)
        elif kind == "cind" and wide:
            refs = ["bbox"] + [f"cube{j}" for j in range(mover)]
            choices = tuple(self.id[r] for r in refs if self.id[r] != token)
        else:
            return None
        return Slot(pos, choices) if choices else None

    def blocks(self, program: Sequence[int], wide: bool) -> list[list[Slot]]:
        out: list[list[Slot]] = []
        mover = -1
        for pos, token in enumerate(program):
            kind = self.kind[token]
            if kind == "start":
                out.append([])
            elif kind == "cuboid":
                mover += 1
                out.append([])
            elif kind == "end":
                break
            elif out:
                slot = self._slot(pos, token, mover, wide)
                if slot is not None:
                    out[-1].append(slot)
        return [b for b in out if b]

    # ---- removal -----------------------------------------------------------------------------
    def removals(self, program: Sequence[int]) -> list[list[int]]:
        """The program without each part k that no later part references (its Cuboid up to the next part or
        END), later references ``cube j`` (j > k) renumbered to ``cube j-1``; [] for a one-part program."""
        starts = [pos for pos, t in enumerate(program) if self.kind[t] == "cuboid"]
        end = next((pos for pos, t in enumerate(program) if self.kind[t] == "end"), len(program))
        if len(starts) < 2:
            return []
        spans = list(zip(starts, starts[1:] + [end]))
        out = []
        for k, (a, b) in enumerate(spans):
            later = program[b:end]
            refs = [self.params[t][0] for t in later if self.kind[t] == "cind"]
            if k in refs:
                continue
            renumbered = [self.id[f"cube{self.params[t][0] - 1}"]
                          if self.kind[t] == "cind" and self.params[t][0] > k else t for t in later]
            out.append(list(program[:a]) + renumbered + list(program[end:]))
        return out

    # ---- insertion ---------------------------------------------------------------------------
    def _cuboids(self, program: Sequence[int]) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
        """(reference name, center, axes (rows), dims) of the bbox and each declared cuboid, as executed."""
        stmts = to_statements(program)
        state = BlockState(stmts[0].args[1], False, lambda parent, i: f"{parent}_ref" if i is None
                           else f"{parent}_trans_{i}")
        state.run(stmts)
        names = ["bbox"] + [n for n in state.cuboids if n.startswith("cube") and "_" not in n]
        return [(n, state.cuboids[n].pos.astype(np.float64), state.cuboids[n].axes.astype(np.float64),
                 state.cuboids[n].dims.astype(np.float64)) for n in names]

    def _placements(self, cuboids, dims: np.ndarray, center: np.ndarray) -> list[tuple[float, list[str]]]:
        """(distance to ``center``, Attach tokens) of the best in-face points of every (cuboid, face), best first.

        A first attach translates the (unrotated) part so that its point q1 meets
        the target's point q2: center = world_target(q2) - (q1 - 0.5) * dims. The
        two in-face coordinates act on their own axes (exactly so for an
        axis-aligned target), so each is chosen over its 9 x 9 (mover, target)
        values separately.
        """
        out = []
        # the mover's offsets per in-face axis (the part's dims): (9,) each
        mover = [(_GRID - 0.5) * dims[a] for a in range(3)]
        for name, pos, axes, bdims in cuboids:
            # the (mover, target) moves per in-face axis a: [i1, i2] = target moved by grid value i2 along axes[a]
            # minus the mover's offset by grid value i1, (9, 9, 3)
            shifts = []
            for a in range(3):
                shift = np.repeat((((_GRID - 0.5) * bdims[a])[:, None] * axes[a][None, :])[None, :, :], 9, 0)
                shift[:, :, a] -= mover[a][:, None]
                shifts.append(shift)
            # error of each face's placement with both in-face points at the face centers: (3,) per face
            resid = []
            for face in FACE_TOKENS:
                q1, q2 = attach_points(face, name == "bbox", (0.5, 0.5), (0.5, 0.5))
                resid.append(pos + ((np.array(q2) - 0.5) * bdims) @ axes - (np.array(q1) - 0.5) * dims - center)
            # the faces of one axis share their in-face axes and moves: both are chosen for them together, the
            # first in-face axis, then the second from the error the first leaves
            found = {}
            for axis, faces in _FACES_BY_AXIS:
                r = np.stack([resid[f] for f in faces])                          # (2, 3)
                picks = []
                for a in (b for b in range(3) if b != axis):
                    miss = r[:, None, None, :] + shifts[a][None]                   # (2, 9, 9, 3)
                    # np.linalg.norm(miss, axis=-1) as numpy computes it, without its checks
                    cost = np.sqrt(np.add.reduce(miss * miss, axis=-1)).reshape(len(faces), 81)
                    i1, i2 = np.divmod(cost.argmin(axis=1), 9)                     # the first minimum, as argmin
                    r = r + shifts[a][i1, i2]
                    picks.append((i1, i2))
                for k, f in enumerate(faces):
                    (m1, t1), (m2, t2) = ((FPOS[i1[k]], FPOS[i2[k]]) for i1, i2 in picks)
                    found[f] = (float(np.sqrt(r[k].dot(r[k]))),        # np.linalg.norm of a vector, as numpy does it
                                ["Attach", name, FACE_TOKENS[f], f"fpos_{m1}_{m2}", f"fpos_{t1}_{t2}"])
            out.extend(found[f] for f in range(len(FACE_TOKENS)))
        out.sort(key=lambda x: x[0])
        return out

    def insertions(self, programs: Sequence[Sequence[int]], outputs: torch.Tensor,
                   targets: torch.Tensor) -> Candidates:
        rows, owner = [], []
        out_np, tgt_np = outputs.numpy(), targets.numpy()
        for i, p in enumerate(programs):
            if p:
                declared = sum(self.kind[t] == "cuboid" for t in p)
                if declared >= MAX_CUBOIDS:
                    continue
                head = [self.table.tokens[t].name for t in p[:-1]]
                try:
                    cuboids = self._cuboids(p)
                except ExecutionError:
                    continue
            else:
                ys = np.nonzero(tgt_np[i].any(axis=(0, 2)))[0]
                if not len(ys):
                    continue
                h = int(np.clip(round(ys[-1] - ys[0] + 1), 1, RES - 1))
                head = ["START", str(h)]
                cuboids = [("bbox", np.zeros(3), np.eye(3), np.array([1.0, h / RES, 1.0]))]
            # boxes grown inside the missed components, not their bounding boxes: parts only
            # add voxels, so a part covering more than the target (e.g. a chair's bounding
            # box) could never be repaired
            for lo, hi in residual_boxes(tgt_np[i] & ~out_np[i], COMPONENTS, bounding=False, grown=GROWN):
                lo_w = np.asarray(lo) / RES - 0.5                 # voxel i spans [i/32 - .5, (i+1)/32 - .5]
                hi_w = (np.asarray(hi) + 1) / RES - 0.5
                size = np.clip(np.round((hi_w - lo_w) * RES), 1, RES - 1)
                part = ["Cuboid"] + [str(int(v)) for v in size]
                for _, attach in self._placements(cuboids, size / RES, (lo_w + hi_w) / 2)[:PLACEMENTS]:
                    for sym in ([], ["Reflect", "X"], ["Reflect", "Z"]):
                        names = head + part + attach + sym + ["END"]
                        if len(names) <= self.max_len:
                            rows.append([self.id[n] for n in names])
                            owner.append(i)
        return Candidates.from_lists(rows, owner)
