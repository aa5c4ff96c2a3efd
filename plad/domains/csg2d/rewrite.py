"""2D CSG's rewriting moves (:class:`plad.domains.space.RewriteSpace`).

* PO blocks: each draw token, together with the operator right after it
  (the one that combines it, in a postfix chain); an operator that follows
  another operator is a block of its own. A draw token's choices are every
  other draw token (``wide``) or its grid neighbours: the same primitive
  with x or y one grid step (8 pixels) or r one step (4 pixels) away, and the
  other primitive kinds at the same x, y, r. An operator's choices are the
  other two operators.
* Expression tree: the postfix stack's sub-expressions; a standalone
  sub-program is its tokens plus ``$``.
* Insertion: every draw token combined with the program by each of the
  insertion operators (union and difference by default) at the root, i.e.
  ``P d op $``; from the empty program, ``d $``. No residual analysis is
  needed: the screen scores all of them. The beam's extensions are the same
  with all three operators (a left-deep chain grows by one primitive).
* Screen: an approximate Chamfer distance computed with bit operations on
  the executor's bit-packed canvases (bit c of word r is pixel [r, c]), ~30
  times cheaper than the exact metric; the ``screen_keep`` best per program
  are scored by the exact Chamfer metric. Edges are the shape's inner
  boundary (a pixel inside with a 4-neighbour outside) instead of Canny's;
  distances are the chessboard distance, counted in steps: a pixel further
  than 0, 1, 3, 7, 15 pixels from the other shape's edges adds 1, 1, 2, 4, 8
  (dilating edges by radius 1, 3, 7, 15 is four doubling steps of shifts).
  Both directed terms are then popcounts. Pixel IoU, the obvious cheaper
  screen, ranks badly for the Chamfer distance: on 30 CAD shapes at the 4th
  greedy insertion, the best exact CD among IoU's 32 best candidates was
  0.11 above the true best, among this screen's 8 best 0.002.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from plad.domains import bits
from plad.domains.bits import row_popcount
from plad.domains.csg2d.executor import pack
from plad.domains.csg2d.tokens import CANVAS, R_VALUES, XY_VALUES
from plad.domains.space import Candidates, Node, RewriteSpace, Slot

_OPERATORS = ("union", "difference", "intersection")
_LOW63 = 0x7FFFFFFFFFFFFFFF
#: dilation steps (radius added per step: 1, 2, 4, 8 -> within 1, 3, 7, 15 pixels) and the
#: weight of lying outside each of the 5 nested regions (the edges, then the 4 dilations)
_STEPS = (1, 2, 4, 8)
_WEIGHTS = (1.0, 1.0, 2.0, 4.0, 8.0)
#: candidates per chunk of the screen (its temporaries then stay small)
_SCREEN_CHUNK = 1024


def _shift_rows(x: torch.Tensor, s: int) -> torch.Tensor:
    """(C, 64) packed canvases: OR of the canvas moved s rows up and s rows down."""
    out = torch.zeros_like(x)
    out[:, s:] = x[:, :-s]
    out[:, :-s] |= x[:, s:]
    return out


def _shift_cols(x: torch.Tensor, s: int) -> torch.Tensor:
    """OR of the canvas moved s columns left and right (logical shifts of the row words)."""
    return (x << s) | ((x >> s) & (_LOW63 >> (s - 1)))


def _edges(x: torch.Tensor) -> torch.Tensor:
    """Inner boundary: pixels inside with a 4-neighbour outside (outside the canvas counts as outside)."""
    left, right = x << 1, (x >> 1) & _LOW63
    up = torch.zeros_like(x)
    up[:, 1:] = x[:, :-1]
    down = torch.zeros_like(x)
    down[:, :-1] = x[:, 1:]
    return x & ~(left & right & up & down)


def _regions(edges: torch.Tensor) -> list[torch.Tensor]:
    """The edges and their chessboard dilations by 1, 3, 7, 15 pixels (nested)."""
    out = [edges]
    for s in _STEPS:
        y = out[-1] | _shift_cols(out[-1], s)
        out.append(y | _shift_rows(y, s))
    return out


def _outside(edges: torch.Tensor, regions: list[torch.Tensor]) -> torch.Tensor:
    """Sum over the edge pixels of the stepped distance to the regions' edges -> float64 (C,)."""
    total = torch.zeros(edges.shape[0], dtype=torch.float64)
    for w, region in zip(_WEIGHTS, regions):
        total += w * row_popcount(edges & ~region).double()
    return total


def _edges_np(x: np.ndarray) -> np.ndarray:
    """:func:`_edges` on numpy words (the same integer operations)."""
    up = np.zeros_like(x)
    up[:, 1:] = x[:, :-1]
    down = np.zeros_like(x)
    down[:, :-1] = x[:, 1:]
    return x & ~((x << 1) & ((x >> 1) & _LOW63) & up & down)


def _regions_np(edges: np.ndarray) -> list[np.ndarray]:
    """:func:`_regions` on numpy words."""
    out = [edges]
    for s in _STEPS:
        y = out[-1] | (out[-1] << s) | ((out[-1] >> s) & (_LOW63 >> (s - 1)))
        rows = np.zeros_like(y)
        rows[:, s:] = y[:, :-s]
        rows[:, :-s] |= y[:, s:]
        out.append(y | rows)
    return out


def _row_counts_np(words: np.ndarray) -> np.ndarray:
    """Set bits per row of (C, 64) int64 words -> int64 (C,) (numpy's popcount, as bits.row_popcount)."""
    return bits._BITWISE_COUNT(words.view(np.uint64)).sum(1, dtype=np.int64)


def _outside_np(edges: np.ndarray, regions: list[np.ndarray]) -> np.ndarray:
    """:func:`_outside` on numpy words: the same float64 sums in the same order."""
    total = np.zeros(edges.shape[0], dtype=np.float64)
    for w, region in zip(_WEIGHTS, regions):
        total += w * _row_counts_np(edges & ~region).astype(np.float64)
    return total


class CSG2DRewrite(RewriteSpace):
    screen_keep = 8
    # a greedy chain of up to 7 primitives, then one round of refinement (more rounds gain little), grafting in
    # every refinement round, from the batch's programs and from the domain's own library (graft_library.npz):
    # grafting pays at every level for about a tenth more time, and the library is what a network's program
    # refined alone (plad infer on one drawing) has to graft from. The library lies in this folder, which every
    # stage that searches lists among its dvc dependencies. The measurements: docs/inference.md ("`plad search`
    # and its effort").
    search_defaults = {"insertions": 7, "refine": {"rounds": 1, "graft": 15, "graft_library": "shipped"}}
    refine_defaults = {"graft": 15, "graft_library": "shipped"}
    # effort levels (measured in docs/inference.md): fast is the search above; default a beam of 2, its 2 best
    # finds refined, no wider so that all 3,000 test shapes search in 10 minutes on 2 workers; best refines
    # all 16 finds of its beam, with a swap, since refining more of a beam pays more than widening it
    search_efforts = {"fast": {}, "default": {"beam_width": 2, "beam_refine": 2},
                      "best": {"beam_width": 16, "beam_refine": 16, "refine": {"swap": True}}}

    def __init__(self, domain, insert_ops: Sequence[str] = ("union", "difference")):
        super().__init__(domain)
        table = domain.tokens
        self.table = table
        #: screen scores in numpy on the CPU (False: in torch everywhere); the same scores
        self.numpy_screen = True
        self.stop = table.index("$")
        self.kind = np.array([t.kind for t in table.tokens])
        self.draws = np.array([i for i, t in enumerate(table.tokens) if t.kind == "draw"], dtype=np.int64)
        self.ops = {t.kind: i for i, t in enumerate(table.tokens) if t.kind in _OPERATORS}
        self.insert_ops = np.array([self.ops[o] for o in insert_ops], dtype=np.int64)
        self.all_ops = np.array([self.ops[o] for o in _OPERATORS], dtype=np.int64)
        self._other_ops = {i: tuple(j for j in self.ops.values() if j != i) for i in self.ops.values()}
        self._all_others = {int(d): tuple(int(e) for e in self.draws if e != d) for d in self.draws}
        self._neighbours = {int(d): self._grid_neighbours(int(d)) for d in self.draws}
        self._is_draw = torch.from_numpy(self.kind == "draw")
        # pseudo draw tokens of an empty and a full canvas (see screen_run)
        V = len(table)
        self._empty, self._full = V, V + 1
        self._extended = domain.executor.extended(
            torch.stack([torch.zeros(CANVAS, CANVAS, dtype=torch.bool), torch.ones(CANVAS, CANVAS, dtype=torch.bool)]))

    def _grid_neighbours(self, token: int) -> tuple[int, ...]:
        kind, x, y, r = self.table.tokens[token].params
        names = []
        for dx, dy, dr in ((-8, 0, 0), (8, 0, 0), (0, -8, 0), (0, 8, 0), (0, 0, -4), (0, 0, 4)):
            if x + dx in XY_VALUES and y + dy in XY_VALUES and r + dr in R_VALUES:
                names.append(f"{kind}({x + dx},{y + dy},{r + dr})")
        names += [f"{k}({x},{y},{r})" for k in ("c", "s", "t") if k != kind]
        return tuple(self.table.index(n) for n in names if self.table.has(n))

    # ---- PO ------------------------------------------------------------------------------
    def blocks(self, program: Sequence[int], wide: bool) -> list[list[Slot]]:
        out: list[list[Slot]] = []
        for pos, tok in enumerate(program):
            kind = self.kind[tok]
            if kind == "draw":
                out.append([Slot(pos, self._all_others[tok] if wide else self._neighbours[tok])])
            elif kind in _OPERATORS:
                slot = Slot(pos, self._other_ops[tok])
                if pos > 0 and self.kind[program[pos - 1]] == "draw":
                    out[-1].append(slot)
                else:
                    out.append([slot])
        return out

    # ---- insertion ---------------------------------------------------------------------------
    def insertions(self, programs: Sequence[Sequence[int]], outputs: torch.Tensor,
                   targets: torch.Tensor) -> Candidates:
        """``P d op $`` for every draw d and insertion operator op (``d $`` from the empty program)."""
        return self._grow(programs, self.insert_ops)

    def extensions(self, programs: Sequence[Sequence[int]], outputs: torch.Tensor,
                   targets: torch.Tensor) -> Candidates:
        """The beam's children: ``P d op $`` for every draw d and every operator (a left-deep chain grows)."""
        return self._grow(programs, self.all_ops)

    def _grow(self, programs: Sequence[Sequence[int]], ops: np.ndarray) -> Candidates:
        """``P d op $`` for every draw d and op in ``ops`` (``d $`` from the empty program).

        Each (program, op) is a template whose draw position takes every draw token.
        """
        templates, owners = [], []
        for i, p in enumerate(programs):
            if not p:
                templates.append([int(self.draws[0]), self.stop])
                owners.append(i)
            elif len(p) + 2 <= self.max_len:
                for op in ops:
                    templates.append(list(p[:-1]) + [int(self.draws[0]), int(op), self.stop])
                    owners.append(i)
        if not templates:
            return Candidates.from_lists([], [])
        bases = Candidates.from_lists(templates, owners)
        D = len(self.draws)
        base = torch.arange(len(templates)).repeat_interleave(D)
        position = torch.where(bases.lengths == 2, 0, bases.lengths - 3)[base]
        tokens = bases.tokens[base]
        tokens[torch.arange(len(tokens)), position] = torch.from_numpy(self.draws).repeat(len(templates))
        return Candidates(tokens, bases.lengths[base], bases.owner[base], bases=bases.tokens, base=base,
                          position=position)

    # ---- CP --------------------------------------------------------------------------------
    def nodes(self, program: Sequence[int]) -> list[Node]:
        spans: list[tuple[int, int, tuple[int, ...]]] = []
        parent: list[int] = []
        stack: list[int] = []
        for pos, tok in enumerate(program):
            kind = self.kind[tok]
            if kind == "draw":
                stack.append(len(spans))
                spans.append((pos, pos + 1, ()))
                parent.append(-1)
            elif kind in _OPERATORS:
                b, a = stack.pop(), stack.pop()
                parent[a] = parent[b] = len(spans)
                stack.append(len(spans))
                spans.append((spans[a][0], pos + 1, (a, b)))
                parent.append(-1)
        return [Node(s, e, c, p) for (s, e, c), p in zip(spans, parent)]

    grafts = True

    def operator(self, program: Sequence[int], node: Node) -> str:
        # postfix: the operator closes the node's span; the executor computes first & ~second for a difference
        return str(self.kind[program[node.end - 1]])

    def standalone(self, program: Sequence[int], node: Node) -> list[int]:
        return list(program[node.start:node.end]) + [self.stop]

    def splice(self, program: Sequence[int], node: Node, expression: Sequence[int]) -> list[int]:
        return list(program[:node.start]) + list(expression[:-1]) + list(program[node.end:])

    # ---- screen ------------------------------------------------------------------------------
    def prepare_screen(self, targets: torch.Tensor) -> tuple:
        packed = pack(targets)                                               # (N, 64) int64
        edges = _edges(packed)
        return edges, _regions(edges), row_popcount(edges)

    def screen_run(self, cands: Candidates) -> torch.Tensor:
        """Packed canvases (C, 64) int64 of the candidates.

        Rows that substitute one draw token of a template (PO, insertion) are
        not executed one by one: a program's output is a pixelwise boolean
        function of each of its draws, so with A0 and A1 the template's outputs
        with that draw replaced by an empty and by a full canvas, the output
        with draw D is ``A0 ^ ((A0 ^ A1) & D)``: two executions per template
        position instead of one per candidate.
        """
        run = self.domain.executor.run_packed
        if cands.base is None:
            return run(cands.tokens)[0]
        rows = torch.arange(len(cands))
        new = cands.tokens[rows, cands.position]
        old = cands.bases[cands.base, cands.position]
        fast = self._is_draw[new] & self._is_draw[old]
        out = torch.empty(len(cands), CANVAS, dtype=torch.int64)
        if not bool(fast.all()):
            out[~fast] = run(cands.tokens[~fast])[0]
        if bool(fast.any()):
            width = cands.bases.shape[1]
            key = cands.base[fast] * width + cands.position[fast]
            unique, inverse = torch.unique(key, return_inverse=True)
            templates = cands.bases[unique // width]
            at = (torch.arange(len(unique)), unique % width)
            templates[at] = self._empty
            a0 = self._extended.run_packed(templates)[0][inverse]
            templates[at] = self._full
            a1 = self._extended.run_packed(templates)[0][inverse]
            out[fast] = a0 ^ ((a0 ^ a1) & self.domain.executor.packed_bitmaps[new[fast]])
        return out

    def screen_score(self, outputs: torch.Tensor, owner: torch.Tensor, prepared: tuple) -> torch.Tensor:
        """Minus the approximate Chamfer distance (higher is better); 16 where an edge map is empty."""
        t_edges, t_regions, t_count = prepared
        if outputs.device.type == "cpu" and bits._BITWISE_COUNT is not None and self.numpy_screen:
            return torch.from_numpy(self._screen_score_np(outputs.numpy(), owner.numpy(), t_edges.numpy(),
                                                          [r.numpy() for r in t_regions], t_count.numpy()))
        out = torch.empty(outputs.shape[0], dtype=torch.float64)
        for start in range(0, outputs.shape[0], _SCREEN_CHUNK):
            sl = slice(start, start + _SCREEN_CHUNK)
            own = owner[sl]
            edges = _edges(outputs[sl])
            count = row_popcount(edges)
            te, tc = t_edges[own], t_count[own]
            to_target = _outside(edges, [r[own] for r in t_regions]) / (count + 1)
            to_pred = _outside(te, _regions(edges)) / (tc + 1)
            cd = (to_target + to_pred) / 2
            out[sl] = -cd.masked_fill((count == 0) | (tc == 0), 16.0)
        return out

    @staticmethod
    def _screen_score_np(outputs: np.ndarray, owner: np.ndarray, t_edges: np.ndarray, t_regions: list[np.ndarray],
                         t_count: np.ndarray) -> np.ndarray:
        """:meth:`screen_score` in numpy (CPU): a screen scores a few dozen candidates at a time, where each
        torch operation's overhead is most of its cost; the same integer steps and float64 sums, the same scores."""
        out = np.empty(outputs.shape[0], dtype=np.float64)
        for start in range(0, outputs.shape[0], _SCREEN_CHUNK):
            sl = slice(start, start + _SCREEN_CHUNK)
            own = owner[sl]
            edges = _edges_np(outputs[sl])
            count = _row_counts_np(edges)
            te, tc = t_edges[own], t_count[own]
            to_target = _outside_np(edges, [r[own] for r in t_regions]) / (count + 1)
            to_pred = _outside_np(te, _regions_np(edges)) / (tc + 1)
            cd = (to_target + to_pred) / 2
            cd[(count == 0) | (tc == 0)] = 16.0
            out[sl] = -cd
        return out
