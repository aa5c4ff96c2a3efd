"""What a domain declares so that the generic rewriters can search its programs.

A domain with search support returns a :class:`RewriteSpace` from its
``rewrite`` member (:attr:`plad.domains.base.Domain.rewrite`). The generic
rewriters (:mod:`plad.rewrite.po`, :mod:`.prune`, :mod:`.insert`) only use
what is declared here, so they never name a domain:

* **moves** for parameter optimization (PO): :meth:`RewriteSpace.blocks`
  groups the program's tokens that may be substituted (a primitive's
  parameters, a draw token, the operators) into blocks of :class:`Slot`; a
  slot lists the tokens that may replace the one at its position. Every
  substitution must give a valid program of the same length.
* **structure** for pruning (CP): :meth:`RewriteSpace.nodes` lists the
  boolean expression tree with each node's token span; :meth:`standalone`
  makes a complete program of a sub-tree and :meth:`splice` replaces a
  sub-tree by another expression. A domain without such a tree returns no
  nodes and is never pruned.
* **removals**: :meth:`RewriteSpace.removals` lists the valid programs with
  one primitive (or part) fewer; from the tree by default, declared by a
  domain without one.
* **candidate generators** for insertion: :meth:`RewriteSpace.insertions`
  proposes programs with one more primitive (or part), from the programs'
  executions and their targets (the residual).
* an optional **screen**: a cheap score of many candidates (e.g. pixel IoU
  on bit-packed canvases) that keeps the ``screen_keep`` best of each group
  before the domain's exact (and possibly expensive) metric.

The empty program (no tokens) is the start of search from scratch; it is
never executed and scores the metric's worst value.
"""
from __future__ import annotations

import abc
import contextlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

from plad.domains.base import Domain


@dataclass(frozen=True)
class Slot:
    """A token of a program that PO may substitute: ``position`` and the token ids that may replace it."""

    position: int
    choices: tuple[int, ...]


@dataclass(frozen=True)
class Node:
    """A sub-expression of a program's expression tree.

    ``start``/``end``: its token span ``[start, end)`` in the program;
    ``children``: indices (in the node list) of its operands, empty for a
    primitive; ``parent``: index of its parent node, -1 for the root.
    """

    start: int
    end: int
    children: tuple[int, ...] = ()
    parent: int = -1

    @property
    def boolean(self) -> bool:
        return bool(self.children)


@dataclass
class Candidates:
    """Candidate programs of many programs, as one padded batch.

    tokens: (C, L) long, each row a complete program followed by padding 0 (ignored by executors);
    lengths: (C,) long, tokens of each program; owner: (C,) long, the index of the
    program (and target) each candidate is for.

    Optional structure a domain's screen may exploit (e.g. to execute a
    template once instead of every row): row c equals ``bases[base[c]]`` with
    the token at ``position[c]`` replaced by ``tokens[c, position[c]]``
    (bases: (T, L) long, base and position: (C,) long).
    """

    tokens: torch.Tensor
    lengths: torch.Tensor
    owner: torch.Tensor
    bases: torch.Tensor | None = None
    base: torch.Tensor | None = None
    position: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.tokens.shape[0]

    def row(self, i: int) -> list[int]:
        return self.tokens[i, : int(self.lengths[i])].tolist()

    def __getitem__(self, index) -> Candidates:
        """The candidates of a slice or index tensor (``bases`` are shared)."""
        def pick(t):
            return None if t is None else t[index]

        return Candidates(self.tokens[index], self.lengths[index], self.owner[index], self.bases,
                          pick(self.base), pick(self.position))

    @staticmethod
    def from_lists(programs: Sequence[Sequence[int]], owner: Sequence[int]) -> Candidates:
        lengths = np.fromiter((len(p) for p in programs), dtype=np.int64, count=len(programs))
        width = max(1, int(lengths.max())) if len(programs) else 1
        tokens = np.zeros((len(programs), width), dtype=np.int64)
        for i, p in enumerate(programs):
            tokens[i, : len(p)] = p
        return Candidates(torch.from_numpy(tokens), torch.from_numpy(lengths),
                          torch.as_tensor(np.asarray(owner, dtype=np.int64)))

    @staticmethod
    def concat(parts: Sequence[Candidates]) -> Candidates:
        """One batch of several; the template structure is kept only if every part has it."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return Candidates(torch.zeros(0, 1, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                              torch.zeros(0, dtype=torch.long))
        width = max(p.tokens.shape[1] for p in parts)
        def widen(t):
            return torch.nn.functional.pad(t, (0, width - t.shape[1]))

        out = Candidates(torch.cat([widen(p.tokens) for p in parts]), torch.cat([p.lengths for p in parts]),
                         torch.cat([p.owner for p in parts]))
        if all(p.bases is not None for p in parts):
            offsets = np.cumsum([0] + [p.bases.shape[0] for p in parts[:-1]])
            out.bases = torch.cat([widen(p.bases) for p in parts])
            out.base = torch.cat([p.base + int(o) for p, o in zip(parts, offsets)])
            out.position = torch.cat([p.position for p in parts])
        return out


class RewriteSpace(abc.ABC):
    """A domain's declaration of its rewriting moves (see the module docstring)."""

    #: Candidates of one group kept by :meth:`screen_score` for the exact metric;
    #: ``None``: the domain has no screen and every candidate is scored exactly.
    screen_keep: int | None = None
    #: Per-domain defaults of :class:`plad.rewrite.driver.SearchConfig` (field -> value).
    search_defaults: ClassVar[dict[str, Any]] = {}
    #: What each effort level of a search (:data:`plad.rewrite.driver.EFFORTS`) changes in
    #: :attr:`search_defaults` (level -> field -> value), each level at least as much work as the one before.
    #: This default, for a domain that has not measured its own: fast skips the refinement after the greedy
    #: insertions, default is :attr:`search_defaults` itself, best refines for up to 3 rounds.
    search_efforts: ClassVar[dict[str, dict[str, Any]]] = {
        "fast": {"refine": {"rounds": 0}}, "default": {}, "best": {"refine": {"rounds": 3}}}

    #: Per-domain settings of :class:`plad.rewrite.driver.RefineConfig` for refining a network's programs
    #: (``plad infer``'s ``default`` and ``best``; field -> value); the class's defaults where not set.
    refine_defaults: ClassVar[dict[str, Any]] = {}
    #: Tokens beyond the language's length cap that the domain's executor and moves handle, so that a search
    #: may grow programs past the cap and shorten them again (``SearchConfig.overshoot``); 0: none
    max_overshoot: ClassVar[int] = 0
    #: whether the domain's expression tree (:meth:`nodes`) has only binary boolean operators that
    #: :meth:`operator` names, so that grafting (``RefineConfig.graft``) can invert them
    grafts: ClassVar[bool] = False

    def __init__(self, domain: Domain):
        self.domain = domain
        #: the longest program insertion proposes, in tokens: the language's length cap (:meth:`longer` lifts it)
        self.max_len = domain.tokens.max_len

    @contextlib.contextmanager
    def longer(self, extra: int):
        """Within the block, insertion proposes programs up to ``extra`` tokens beyond the length cap (at most
        :attr:`max_overshoot`); such programs are for a search to shorten, never to return."""
        if not 0 <= extra <= self.max_overshoot:
            raise ValueError(f"{self.domain.name}: {extra} tokens beyond the length cap; the domain allows "
                             f"0 to {self.max_overshoot}")
        cap = self.max_len
        self.max_len = cap + extra
        try:
            yield
        finally:
            self.max_len = cap

    # ---- PO -------------------------------------------------------------------------------
    @abc.abstractmethod
    def blocks(self, program: Sequence[int], wide: bool) -> list[list[Slot]]:
        """Blocks of substitutable tokens of a valid non-empty program, in token order.

        PO tries every single-slot substitution of one block at a time and
        keeps the best. ``wide``: the domain's large choice sets (e.g. every
        draw token); otherwise local neighbours only (e.g. +-1, +-2).
        """

    # ---- insertion --------------------------------------------------------------------------
    @abc.abstractmethod
    def insertions(self, programs: Sequence[Sequence[int]], outputs: torch.Tensor,
                   targets: torch.Tensor) -> Candidates:
        """Programs with one more primitive (or part), for each of ``programs``.

        ``outputs``: their executions (B, *shape) bool (all False for an empty
        program), ``targets``: (B, *shape) bool. Candidates' owners index
        ``programs``. The inserted tokens must form the program's last PO block
        (so that :func:`plad.rewrite.po.optimize` with ``last_only`` tunes them).
        """

    def extensions(self, programs: Sequence[Sequence[int]], outputs: torch.Tensor,
                   targets: torch.Tensor) -> Candidates:
        """The children of partial programs in beam search (:mod:`plad.rewrite.beam`): programs one
        primitive (or part) longer, arguments as :meth:`insertions`. A beam explores where a greedy
        insertion would not, so a domain may offer more here (e.g. every operator, not only those that
        pay greedily). Default: :meth:`insertions`."""
        return self.insertions(programs, outputs, targets)

    def seeds(self, targets: torch.Tensor) -> list[list[int]] | None:
        """One program per target (B, *shape) bool from which a search may also start (``SearchConfig.seeded``),
        e.g. a primitive covering the whole shape that differences then carve; ``[]`` for a target without one.
        None: the domain offers no seeds (the default)."""
        return None

    # ---- CP ---------------------------------------------------------------------------------
    def nodes(self, program: Sequence[int]) -> list[Node]:
        """The expression tree of a valid program, children before parents; [] if none."""
        return []

    def standalone(self, program: Sequence[int], node: Node) -> list[int]:
        """A complete program executing to the node's sub-expression."""
        raise NotImplementedError

    def splice(self, program: Sequence[int], node: Node, expression: Sequence[int]) -> list[int]:
        """``program`` with the node's sub-expression replaced by the expression of the
        standalone program ``expression`` (as returned by :meth:`standalone`)."""
        raise NotImplementedError

    def operator(self, program: Sequence[int], node: Node) -> str:
        """The boolean operator of a node with children (``nodes``): "union", "intersection" or "difference"
        (its first operand minus its second), for grafting (:mod:`plad.rewrite.graft`), which inverts it."""
        raise NotImplementedError(f"{self.domain.name}: no boolean operators to graft through")

    def without(self, program: Sequence[int], nodes: list[Node], n: int) -> list[int] | None:
        """The program without node ``n`` (of ``nodes``, its tree): its parent replaced by its only sibling;
        None for the root or a parent with more than two operands."""
        if nodes[n].parent < 0:
            return None
        parent = nodes[nodes[n].parent]
        siblings = [c for c in parent.children if c != n]
        if len(siblings) != 1:
            return None
        return self.splice(program, parent, self.standalone(program, nodes[siblings[0]]))

    # ---- removal ----------------------------------------------------------------------------
    def removals(self, program: Sequence[int]) -> list[list[int]]:
        """Valid programs with one primitive (or part) of ``program`` removed, in token order; [] if none may
        be. Default: each leaf of the expression tree (:meth:`nodes`) removed by :meth:`without`; a domain
        without a tree declares its own."""
        if not program:
            return []
        nodes = self.nodes(program)
        shorter = (self.without(program, nodes, n) for n, node in enumerate(nodes) if not node.boolean)
        return [p for p in shorter if p is not None]

    # ---- screen -----------------------------------------------------------------------------
    def prepare_screen(self, targets: torch.Tensor) -> Any:
        """Per-target data of the screen (e.g. bit-packed targets), computed once per target set."""
        return None

    def screen_run(self, cands: Candidates) -> torch.Tensor:
        """Execute candidates in the screen's own representation (e.g. bit-packed), (C, ...)."""
        raise NotImplementedError

    def screen_score(self, outputs: torch.Tensor, owner: torch.Tensor, prepared: Any) -> torch.Tensor:
        """Cheap score (C,) float of :meth:`screen_run` outputs against targets ``owner``; higher is better."""
        raise NotImplementedError
