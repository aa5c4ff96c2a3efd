"""3D CSG's rewriting moves (:class:`plad.domains.space.RewriteSpace`).

* PO blocks: first one block with every boolean operator (each may become
  one of the other two), then one block per primitive, in token order: its
  kind (cuboid <-> ellipsoid) and its six integer parameters, each moved by
  +-1 or +-2 (``wide``: also +-4 and +-8) within 1..31.
* Expression tree: the prefix expression's sub-expressions; a sub-tree's
  tokens are a complete program by themselves.
* Insertion, from the residual's connected components (6-connected): the
  largest components of the missed voxels (target and not program) become a
  ``union`` with a cuboid (or an ellipsoid) fitted to the component's
  bounding box, or to boxes grown inside the component (from its deepest
  voxel, then from the deepest ones earlier boxes leave uncovered); the
  largest components of the extra voxels (program and not target) a
  ``diff``. (A bounding box alone fails for the extra voxels: the empty
  space around a chair inside its box is one component whose bounding box
  is the whole shape.) ``union P B`` keeps the new primitive last, so it is
  the program's last PO block.
* Screen: the exact IoU computed on the executor's bit-packed grids (no
  unpacking), so one candidate per program is kept for the domain metric.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from plad.domains.bits import packed_iou
from plad.domains.boxes import residual_boxes
from plad.domains.csg3d.executor import EMPTY_PRIMITIVE, FULL_PRIMITIVE, pack, render_primitives
from plad.domains.csg3d.tokens import N_PARAMS, OPERATORS, PARAM_MAX, PARAM_MIN, PRIMITIVES
from plad.domains.space import Candidates, Node, RewriteSpace, Slot

#: the language's operators by the names grafting knows them by (plad.rewrite.graft)
_OPERATOR_NAMES = {"union": "union", "inter": "intersection", "diff": "difference"}
#: parameter steps of PO
LOCAL_STEPS = (-2, -1, 1, 2)
WIDE_STEPS = (-8, -4, -2, -1, 1, 2, 4, 8)
#: components of each residual (missed, extra) turned into insertion candidates, and boxes grown
#: in each (on 100 PartNet test shapes: IoU 0.884 with one grown box, 0.913 with 3, 0.914 with 5)
COMPONENTS = 2
GROWN = 3


def fit_box(lo: Sequence[int], hi: Sequence[int]) -> list[int]:
    """Parameters ``x y z dx dy dz`` of the smallest cuboid covering voxels lo..hi (inclusive) per axis.

    A cuboid covers ``|p - c| <= d/2``, i.e. an odd number 2 floor(d/2) + 1 of
    voxels around an integer center; parameters are clipped to 1..31.
    """
    c, d = [], []
    for a, b in zip(lo, hi):
        center = min(max((a + b) // 2, PARAM_MIN), PARAM_MAX)
        half = max(center - a, b - center, 0)
        c.append(center)
        d.append(min(max(2 * half + 1, PARAM_MIN), PARAM_MAX))
    return c + d


class CSG3DRewrite(RewriteSpace):
    screen_keep = 1
    # the executor runs programs of any length (a left-deep chain of 25 primitives: 199 tokens)
    max_overshoot = 100
    # up to 12 primitives, each tuned by +-1/+-2 coordinate descent until no gain (capped at 60 moves), then
    # one round of refinement
    search_defaults = {"insertions": 12, "tune_sweeps": 60, "refine": {"rounds": 1}}
    # effort levels (measured in docs/inference.md): fast skips the refinement; default is the search above;
    # best runs that search and a beam of 4 over partial programs (the tuned one-at-a-time insertion and the
    # beam's lookahead win on different shapes), each refined for up to 3 rounds with a swap. Most of what it
    # still loses is the 12-primitive cap, so it also starts from the shape's bounding cuboid, which
    # differences carve (seeded), and from one program grown to 16 cuboids (overshoot 28 tokens) that backward
    # elimination brings back to 12; each start replaces the shape's program where better
    search_efforts = {**RewriteSpace.search_efforts,
                      "best": {"beam_width": 4, "beam_refine": 2, "greedy_first": True, "seeded": True,
                               "overshoot": 28, "refine": {"rounds": 3, "swap": True}}}

    def __init__(self, domain):
        super().__init__(domain)
        table = domain.tokens
        self.kind = [t.kind for t in table.tokens]
        self.value = np.array([t.params[0] if t.kind == "num" else 0 for t in table.tokens])
        self.num = {v: table.index(str(v)) for v in range(PARAM_MIN, PARAM_MAX + 1)}
        self.prim = {p: table.index(p) for p in PRIMITIVES}
        self.op = {o: table.index(o) for o in OPERATORS}
        self._op_name = {i: o for o, i in self.op.items()}
        self._other = {i: tuple(j for j in group.values() if j != i)
                       for group in (self.prim, self.op) for i in group.values()}
        self._is_op = torch.tensor([k == "operator" for k in self.kind] + [False, False])
        self._is_prim = torch.tensor([k == "primitive" for k in self.kind] + [True, True])
        self._value = torch.from_numpy(np.concatenate([self.value, [0, 0]]))

    # ---- PO -------------------------------------------------------------------------------
    def _choices(self, token: int, wide: bool) -> tuple[int, ...]:
        v = int(self.value[token])
        return tuple(self.num[v + s] for s in (WIDE_STEPS if wide else LOCAL_STEPS)
                     if PARAM_MIN <= v + s <= PARAM_MAX)

    def blocks(self, program: Sequence[int], wide: bool) -> list[list[Slot]]:
        ops = [Slot(pos, self._other[t]) for pos, t in enumerate(program) if self.kind[t] == "operator"]
        out = [ops] if ops else []
        for pos, t in enumerate(program):
            if self.kind[t] == "primitive":
                out.append([Slot(pos, self._other[t])]
                           + [Slot(pos + 1 + k, self._choices(program[pos + 1 + k], wide)) for k in range(N_PARAMS)])
        return out

    # ---- insertion ---------------------------------------------------------------------------
    def insertions(self, programs: Sequence[Sequence[int]], outputs: torch.Tensor,
                   targets: torch.Tensor) -> Candidates:
        rows, owner = [], []
        out_np, tgt_np = outputs.numpy(), targets.numpy()
        for i, p in enumerate(programs):
            if len(p) + (1 + 1 + N_PARAMS if p else 1 + N_PARAMS) > self.max_len:
                continue
            for op, mask in (("union", tgt_np[i] & ~out_np[i]), ("diff", out_np[i] & ~tgt_np[i])):
                if not p and op == "diff":
                    continue
                for lo, hi in residual_boxes(mask, COMPONENTS, grown=GROWN):
                    params = [self.num[v] for v in fit_box(lo, hi)]
                    for prim in PRIMITIVES:
                        new = [self.prim[prim]] + params
                        rows.append([self.op[op]] + list(p) + new if p else new)
                        owner.append(i)
        return Candidates.from_lists(rows, owner)

    def seeds(self, targets: torch.Tensor) -> list[list[int]]:
        """The cuboid around each target's voxels: a start that differences carve (a table is its box less
        the space under its top: 3 primitives, where unions take 5), which greedy insertion from the empty
        program, taking the box that pays most at once, seldom builds."""
        out = []
        for t in targets.numpy():
            idx = np.nonzero(t)
            if not len(idx[0]):
                out.append([])
                continue
            box = fit_box([int(a.min()) for a in idx], [int(a.max()) for a in idx])
            out.append([self.prim["cuboid"]] + [self.num[v] for v in box])
        return out

    # ---- CP --------------------------------------------------------------------------------
    def nodes(self, program: Sequence[int]) -> list[Node]:
        spans: list[list] = []          # [start, end, children, parent]

        def parse(pos: int) -> tuple[int, int]:
            if self.kind[program[pos]] == "primitive":
                spans.append([pos, pos + 1 + N_PARAMS, (), -1])
                return len(spans) - 1, pos + 1 + N_PARAMS
            a, mid = parse(pos + 1)
            b, end = parse(mid)
            spans.append([pos, end, (a, b), -1])
            spans[a][3] = spans[b][3] = len(spans) - 1
            return len(spans) - 1, end

        parse(0)
        return [Node(s, e, c, p) for s, e, c, p in spans]

    grafts = True

    def operator(self, program: Sequence[int], node: Node) -> str:
        # prefix: the operator opens the node's span; the executor computes first & ~second for a difference
        return _OPERATOR_NAMES[self._op_name[program[node.start]]]

    def standalone(self, program: Sequence[int], node: Node) -> list[int]:
        return list(program[node.start:node.end])

    def splice(self, program: Sequence[int], node: Node, expression: Sequence[int]) -> list[int]:
        return list(program[:node.start]) + list(expression) + list(program[node.end:])

    # ---- screen ------------------------------------------------------------------------------
    def prepare_screen(self, targets: torch.Tensor) -> torch.Tensor:
        return pack(targets)                                               # (N, 32, 32) int32

    def screen_run(self, cands: Candidates) -> torch.Tensor:
        """Packed grids (C, 32, 32) int32 of the candidates.

        Rows that change one primitive of a template (PO) are not executed one
        by one: the output is a voxelwise boolean function of that primitive's
        grid G, so with A0 and A1 the template's outputs with the primitive
        drawing the empty and the full grid (the executor's pseudo primitives),
        the output is ``A0 ^ ((A0 ^ A1) & G)``.
        """
        run = self.domain.executor.run_packed
        if cands.base is None:
            return run(cands.tokens)[0]
        C = len(cands)
        rows = torch.arange(C)
        old = cands.bases[cands.base, cands.position]
        new = cands.tokens[rows, cands.position]
        fast = ~self._is_op[old] & ~self._is_op[new]
        out = torch.empty(C, 32, 32, dtype=torch.int32)
        if not bool(fast.all()):
            out[~fast] = run(cands.tokens[~fast])[0]
        if bool(fast.any()):
            # the primitive each substituted token belongs to: the last primitive token at or before it
            width = cands.bases.shape[1]
            at = torch.arange(width)
            owner_pos = torch.where(self._is_prim[cands.bases], at, -1).cummax(dim=1).values    # (T, L)
            f_rows = rows[fast]
            prim = owner_pos[cands.base[fast], cands.position[fast]]                           # (F,)
            key = cands.base[fast] * width + prim
            unique, inverse = torch.unique(key, return_inverse=True)
            templates = cands.bases[unique // width]
            where = (torch.arange(len(unique)), unique % width)
            templates[where] = EMPTY_PRIMITIVE
            a0 = run(templates)[0][inverse]
            templates[where] = FULL_PRIMITIVE
            a1 = run(templates)[0][inverse]
            params = self._value[cands.tokens[f_rows[:, None], prim[:, None] + torch.arange(1, 1 + N_PARAMS)]]
            grid = render_primitives(params, cands.tokens[f_rows, prim] == self.prim["ellipsoid"])
            out[fast] = a0 ^ ((a0 ^ a1) & grid)
        return out

    def screen_score(self, outputs: torch.Tensor, owner: torch.Tensor, prepared: torch.Tensor) -> torch.Tensor:
        return packed_iou(outputs, prepared[owner])
