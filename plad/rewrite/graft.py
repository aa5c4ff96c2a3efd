"""Code grafting (CG), as SIRI does it: replace a sub-expression by a cached one that executes to what the
node should.

For every node of a program's expression tree
(:meth:`~plad.domains.space.RewriteSpace.nodes`) the **desired execution** follows from the target by
inverting the boolean operators above it (:func:`desired`): the root should execute to the target; below a
union, where the sibling is full, the child may be anything; below an intersection, where the sibling is
empty; the first operand of a difference, where the second is full; the second operand, where the first is
empty, and elsewhere it should be the complement of what its parent should be. So each node gets a wanted
execution and a mask of the pixels (voxels) that matter.

The **library** is every sub-expression of a set of programs (by default the batch's own programs, so shapes
lend each other their parts, as SIRI's cache of P_BEST's sub-expressions does), one per distinct execution
(the shortest). For each node the ``k`` entries whose executions differ least from the wanted one on its
mask (a Hamming distance, by one matrix product) are spliced in; every candidate is executed and scored
exactly, and each program takes its best where that improves it (metric, then fewer tokens). Programs that
improved are grafted again, up to ``rewrites`` times.
"""
from __future__ import annotations

import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from plad.domains.space import Node
from plad.rewrite.evaluate import Scorer
from plad.rewrite.insert import improve_repeatedly

#: SIRI: the 15 nearest cached sub-expressions per node, at most 10 rewrites per program
NEAREST = 15
REWRITES = 10
#: elements of a float32 temporary of the distance product (queries or entries x pixels per block)
_BLOCK_ELEMENTS = 1 << 24


def desired(space, program: Sequence[int], nodes: list[Node], outputs: torch.Tensor, target: torch.Tensor,
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """What each node of ``program`` should execute to: (want, care), both (len(nodes), D) bool.

    ``outputs``: the nodes' executions (len(nodes), *shape) bool; ``target`` (*shape) bool. Where ``care`` is
    False the program's execution does not depend on the node's; where it is True the program's execution
    equals the target there exactly when the node's execution equals ``want``.
    """
    n = len(nodes)
    flat = outputs.reshape(n, -1)
    want = torch.empty_like(flat)
    care = torch.empty_like(flat)
    root = next(i for i, node in enumerate(nodes) if node.parent < 0)
    want[root] = target.reshape(-1)
    care[root] = True
    # parents come after their children in ``nodes``: walk them from the root down
    for i in reversed(range(n)):
        node = nodes[i]
        if not node.boolean:
            continue
        if len(node.children) != 2:
            raise ValueError(f"grafting: node {i} has {len(node.children)} operands; only binary operators invert")
        a, b = node.children
        op = space.operator(program, node)
        if op == "union":         # a | b: a matters where b is empty
            want[a], care[a] = want[i], care[i] & ~flat[b]
            want[b], care[b] = want[i], care[i] & ~flat[a]
        elif op == "intersection":  # a & b: a matters where b is full
            want[a], care[a] = want[i], care[i] & flat[b]
            want[b], care[b] = want[i], care[i] & flat[a]
        elif op == "difference":  # a & ~b: a where b is empty; b, complemented, where a is full
            want[a], care[a] = want[i], care[i] & ~flat[b]
            want[b], care[b] = ~want[i], care[i] & flat[a]
        else:
            raise ValueError(f"grafting: operator {op!r} of node {i}: expected union, intersection or difference")
    return want, care


def _execute(domain, programs: Sequence[Sequence[int]], chunk: int = 4096) -> torch.Tensor:
    """Executions (N, *shape) bool of valid programs, ``chunk`` at a time (a library may hold many)."""
    from plad.domains.base import pad_programs

    if not programs:
        return torch.zeros(0, *domain.shape, dtype=torch.bool)
    return torch.cat([domain.execute(pad_programs(programs[s:s + chunk])).bool()
                      for s in range(0, len(programs), chunk)])


@dataclass
class Library:
    """Distinct sub-expressions: ``programs`` (standalone token lists) and their executions (M, D) bool."""

    programs: list[list[int]]
    executions: torch.Tensor
    _dense: torch.Tensor | None = field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.programs)

    @staticmethod
    def build(programs: Sequence[Sequence[int]], outputs: torch.Tensor) -> Library:
        """From standalone ``programs`` and their executions (M, *shape) bool: one per distinct execution, the
        shortest (then the first); empty and full executions are left out (pruning handles those)."""
        flat = outputs.reshape(len(programs), -1)
        keep: dict[bytes, int] = {}
        filled = flat.any(1) & ~flat.all(1)
        for j in torch.nonzero(filled).flatten().tolist():
            key = flat[j].numpy().tobytes()
            if key not in keep or len(programs[j]) < len(programs[keep[key]]):
                keep[key] = j
        rows = sorted(keep.values())
        return Library([list(programs[j]) for j in rows], flat[rows].clone())

    def save(self, path: str | Path, domain) -> None:
        """Write the programs (their executions are recomputed on loading), atomically."""
        from plad.fsutil import atomic_write, savez

        width = max((len(p) for p in self.programs), default=1)
        tokens = np.full((len(self), width), -1, dtype=np.int16)
        for i, p in enumerate(self.programs):
            tokens[i, :len(p)] = p
        atomic_write(Path(path), lambda fh: savez(fh, tokens=tokens, domain=np.array(domain.name)))

    @staticmethod
    def load(path: str | Path, domain) -> Library:
        """A library written by :meth:`save` for ``domain``; ValueError naming the file if it is not one."""
        path = Path(path)
        if not zipfile.is_zipfile(path):
            raise ValueError(f"{path}: not a grafting library (not an .npz archive)")
        try:
            with np.load(path, allow_pickle=False) as f:
                tokens, name = f["tokens"], str(f["domain"])
        except (OSError, KeyError, ValueError) as err:
            raise ValueError(f"{path}: not a grafting library ({err})") from None
        if name != domain.name:
            raise ValueError(f"{path}: a grafting library of {name}, not of {domain.name}")
        programs = [[int(t) for t in row if t >= 0] for row in tokens]
        for i, p in enumerate(programs):
            try:
                domain.check(p)
            except Exception as err:
                raise ValueError(f"{path}: program {i} is not a valid {domain.name} program: {err}") from None
        return Library.build(programs, _execute(domain, programs))

    def dense(self) -> torch.Tensor:
        """The executions as float32 (M, D), made once per library (a loaded library is kept per process, so
        refining shape after shape does not convert its executions again)."""
        if self._dense is None:
            self._dense = self.executions.float()
        return self._dense

    def nearest(self, want: torch.Tensor, care: torch.Tensor, k: int) -> torch.Tensor:
        """The ``k`` entries nearest to ``want`` on ``care``: :func:`nearest` of this library alone."""
        return nearest([self], want, care, k)


def nearest(libraries: Sequence[Library], want: torch.Tensor, care: torch.Tensor, k: int) -> torch.Tensor:
    """The ``k`` entries (fewer if the libraries hold fewer) whose executions differ least from ``want`` on
    ``care`` (Q, D) bool -> (Q, k) indices into the libraries' entries one after another, nearest first.

    The masked Hamming distance sum(care & (want ^ e)) is |care & want| + s . e with s = care * (1 - 2 want)
    in {-1, 0, 1}: one matrix product per library, exact in float32 (counts below 2^24).
    """
    total = sum(len(lib) for lib in libraries)
    k = min(k, total)
    q = want.shape[0]
    out = torch.empty(q, k, dtype=torch.long)
    if k == 0:
        return out
    block = max(1, _BLOCK_ELEMENTS // max(want.shape[1], total))
    for s in range(0, q, block):
        w, c = want[s:s + block], care[s:s + block]
        signed = c.float() * (1 - 2 * w.float())                       # (q', D)
        base = (c & w).sum(1, keepdim=True).float()
        dist = torch.cat([base + signed @ lib.dense().T for lib in libraries if len(lib)], dim=1)   # (q', total)
        out[s:s + block] = torch.topk(dist, k, dim=1, largest=False).indices
    return out


#: the file name of a domain's own library (:func:`library_path`), in its plugin's package
SHIPPED = "graft_library.npz"
_LOADED: dict[tuple[str, str], Library] = {}


def shipped_library(domain) -> Path:
    """Where the domain's own library lives: ``plad/domains/<domain>/graft_library.npz`` (package data)."""
    import inspect

    return Path(inspect.getfile(type(domain))).parent / SHIPPED


def library_path(domain, name: str) -> Path:
    """The file of a library setting: ``"shipped"`` (the domain's own, :func:`shipped_library`) or a path;
    ValueError if there is no such file."""
    if name == "shipped":
        path = shipped_library(domain)
        if not path.is_file():
            raise ValueError(f"graft_library = shipped: {domain.name} ships no grafting library ({path}); build one "
                             f"with python -m plad.tools.graft_library {domain.name}")
        return path
    path = Path(name)
    if not path.is_file():
        raise ValueError(f"graft_library = {name}: no such file")
    return path


def load_library(domain, name: str) -> Library:
    """The library of a setting (:func:`library_path`), loaded once per process."""
    path = library_path(domain, name)
    key = (domain.name, str(path.resolve()))
    if key not in _LOADED:
        _LOADED[key] = Library.load(path, domain)
    return _LOADED[key]


def _trees(scorer: Scorer, programs: list[list[int]], rows: Sequence[int]):
    """Each row's nodes and the nodes' standalone programs and executions (one batch for all rows)."""
    space = scorer.space
    trees, subprograms, spans = {}, [], {}
    for i in rows:
        nodes = space.nodes(programs[i]) if programs[i] else []
        if nodes:
            trees[i] = nodes
            spans[i] = (len(subprograms), len(subprograms) + len(nodes))
            subprograms += [space.standalone(programs[i], node) for node in nodes]
    outputs = scorer.outputs(subprograms) if subprograms else None
    return trees, subprograms, spans, outputs


def graft(scorer: Scorer, programs: list[list[int]], values: torch.Tensor, k: int = NEAREST,
          rewrites: int = REWRITES, library: Library | None = None, extra: Library | None = None,
          ) -> tuple[list[list[int]], torch.Tensor]:
    """Graft into every program (see the module docstring); returns (programs, values), never worse.

    ``library``: the sub-expressions to graft; None: those of ``programs`` as they are on entry, with those of
    ``extra`` (e.g. a library shipped with the model: :func:`load_library`).
    """
    space = scorer.space
    libraries: list[Library] = []   # fixed by the first round: the libraries, and their entries one after another
    entries: list[list[int]] = []

    def propose(current: list[list[int]], rows: list[int]) -> tuple[list[list[int]], list[int]]:
        trees, subprograms, spans, outputs = _trees(scorer, current, rows)
        if not trees:
            return [], []
        if not libraries:   # None: the programs as they are on entry
            libraries.append(Library.build(subprograms, outputs) if library is None else library)
            if extra is not None:
                libraries.append(extra)
            entries.extend(p for lib in libraries for p in lib.programs)
        if not entries:
            return [], []
        wants, cares, where = [], [], []
        for i, nodes in trees.items():
            a, b = spans[i]
            want, care = desired(space, current[i], nodes, outputs[a:b], scorer.targets[i])
            wants.append(want)
            cares.append(care)
            where += [(i, n) for n in range(len(nodes))]
        near = nearest(libraries, torch.cat(wants), torch.cat(cares), k)
        cands, owner = [], []
        for (i, n), hits in zip(where, near.tolist()):
            for h in hits:
                new = space.splice(current[i], trees[i][n], entries[h])
                if len(new) <= space.max_len and new != current[i]:
                    cands.append(new)
                    owner.append(i)
        return cands, owner

    return improve_repeatedly(scorer, programs, values, propose, rewrites, "graft")


def sub_expressions(domain, programs: Sequence[Sequence[int]]) -> Library:
    """The library of every sub-expression of ``programs`` (e.g. programs found for training shapes)."""
    space = domain.rewrite
    subprograms = [space.standalone(p, node) for p in programs if p for node in space.nodes(p)]
    return Library.build(subprograms, _execute(domain, subprograms))


__all__ = ["NEAREST", "REWRITES", "SHIPPED", "Library", "desired", "graft", "library_path",
           "load_library", "nearest", "shipped_library",
           "sub_expressions"]
