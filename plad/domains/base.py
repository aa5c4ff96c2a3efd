"""The domain plugin protocol.

A domain is everything that is specific to one shape language: its token
table (grammar), the text form of programs, a batched executor, a synthetic
program sampler, where its target (real) data comes from, its metric, its RL
reward and how results are shown next to the paper's. Model, search,
training methods, stages, the command line and the report stay generic and
only talk to this; a plugin (``plad/domains/<name>/``) imports no other plugin.

Required members are abstract. Optional members have a documented default
that means "the domain does not offer this"; callers ask the domain through
them, never by probing for attributes.
"""
from __future__ import annotations

import abc
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from plad.data.files import TargetSource
from plad.domains.grammar import ProgramError, TokenTable
from plad.metrics import Metric

_NONE: Mapping[str, float] = MappingProxyType({})
_NONE_EDITS: Mapping[str, Callable] = MappingProxyType({})


#: a program edit of a domain (:meth:`Domain.edits`): (valid program, donor programs, rng) -> a valid program
#: within the length cap, or None where it cannot
Edit = Callable[[Sequence[int], Sequence[Sequence[int]], np.random.Generator], "list[int] | None"]


@dataclass(frozen=True)
class Symmetry:
    """A symmetry of a domain's grammar (:meth:`Domain.symmetries`): a map of programs whose execution is
    the original's transformed by a symmetry of the grid.

    The grid transform is a signed permutation of the shape's axes: axis ``i`` of the transformed shape is
    axis ``axes[i]`` of the original, reversed where ``flips[i]``. ``program`` maps a valid program to a
    valid program of the same length, or returns None where the grammar cannot express the image (e.g. a
    primitive that exists only upright, a parameter that leaves its range). Applying it :attr:`order` times
    gives back the original program exactly.

    ``exact``: every program it maps executes to exactly :meth:`grid` of the original's execution;
    otherwise the rasterization makes that approximate (the domain's module says why and how much) and
    ``mean_iou`` is the bound the tests hold the mean IoU between the two to, over sampled programs (one
    program may have no bound: a one-pixel shift can erase a thin sliver).
    """

    name: str
    program: Callable[[Sequence[int]], list[int] | None]
    axes: tuple[int, ...]
    flips: tuple[bool, ...]
    exact: bool = True
    mean_iou: float = 1.0

    def grid(self, shapes):
        """The grid transform of executions (..., *shape), a numpy array or a torch tensor (the same type)."""
        k = len(self.axes)
        lead = shapes.ndim - k
        perm = list(range(lead)) + [lead + a for a in self.axes]
        flipped = [lead + i for i, f in enumerate(self.flips) if f]
        if isinstance(shapes, torch.Tensor):
            out = shapes.permute(perm)
            return out.flip(flipped) if flipped else out
        out = np.transpose(shapes, perm)
        return np.flip(out, flipped) if flipped else out

    @property
    def order(self) -> int:
        """The least n > 0 with the grid transform applied n times the identity (2: an involution, 4: a
        quarter turn)."""
        axes, flips = tuple(range(len(self.axes))), (False,) * len(self.axes)
        for n in range(1, 2 * len(self.axes) + 1):
            axes, flips = (tuple(axes[a] for a in self.axes),
                           tuple(flips[a] != f for a, f in zip(self.axes, self.flips)))
            if axes == tuple(range(len(axes))) and not any(flips):
                return n
        raise AssertionError("a signed permutation has finite order")


class Domain(abc.ABC):
    """Base class of domain plugins. Subclasses set the class attributes and implement the methods."""

    #: registry name (the key of :func:`plad.domains.get_domain`), lower case
    name: str
    #: shape of one executed program / target, e.g. ``(64, 64)`` or ``(32, 32, 32)``
    shape: tuple[int, ...]
    #: the domain's reconstruction metric (declares whether higher is better)
    metric: Metric
    #: optional: program rewriting and search support, a :class:`plad.domains.space.RewriteSpace` (the moves,
    #: program structure and candidate generators of :mod:`plad.rewrite`); None: the domain has no search
    #: support. Not annotated with the class: ``plad.domains.space`` imports this module.
    rewrite: Any = None

    # -- how results are shown (optional) ---------------------------------------------------
    #: name in tables and figures, e.g. ``"2D CSG"``; default: the registry name
    title: str = ""
    #: factor the metric is shown with in tables and figures (e.g. 100 for IoU in percent)
    display_scale: float = 1.0
    #: decimals of the shown (scaled) metric
    display_digits: int = 3
    #: the paper's Table 1 (test set, beam 10) for this domain: method key -> value in display units;
    #: default: none
    paper_table: Mapping[str, float] = _NONE
    #: the paper supplement's numbers with P_BEST reset every round: method key -> value in display units;
    #: default: none
    paper_per_round: Mapping[str, float] = _NONE

    @property
    def display_name(self) -> str:
        """:attr:`title`, else the registry name."""
        return self.title or self.name

    @property
    @abc.abstractmethod
    def tokens(self) -> TokenTable:
        """The token table; it alone defines validity, decoding masks and the length cap."""

    # -- text form ---------------------------------------------------------------
    @abc.abstractmethod
    def parse(self, text: str) -> list[int]:
        """Program text -> token ids. Raises :class:`ProgramError` naming the bad token."""

    @abc.abstractmethod
    def format(self, ids: Sequence[int]) -> str:
        """Token ids -> program text (the inverse of :meth:`parse` for valid programs)."""

    def check(self, ids: Sequence[int]) -> None:
        """Raise :class:`ProgramError` if ``ids`` is not a complete valid program."""
        self.tokens.check(ids)

    # -- execution -----------------------------------------------------------------
    @abc.abstractmethod
    def execute(self, programs: torch.Tensor) -> torch.Tensor:
        """Execute a batch of valid programs.

        ``programs``: (B, L) long token ids, each row a complete valid program
        followed by any padding (ignored). Returns (B, *shape) bool on the
        same device.
        """

    # -- synthetic data ----------------------------------------------------------------
    @abc.abstractmethod
    def sample(self, n: int, generator: np.random.Generator) -> list[list[int]]:
        """``n`` valid, non-degenerate synthetic programs for supervised pretraining."""

    def samplers(self) -> dict[str, Callable[[int, np.random.Generator], list[list[int]]]]:
        """The synthetic samplers this domain offers, by name (params ``synthesize.<domain>.sampler``):
        ``"paper"`` is :meth:`sample` (the paper's), a domain may add its own beyond the paper."""
        return {"paper": self.sample}

    def canonical(self, ids: Sequence[int]) -> list[int]:
        """The canonical form of the valid program ``ids``: a program with exactly the same execution,
        the same for every program of its class (e.g. commutative operands in a fixed order).

        Training labels (synthetic programs, P_BEST entries) are rewritten into it, so that the
        network is not asked to guess a free choice that the execution cannot show. It never
        makes a program longer. Default: the program itself (the domain has no such choices).
        """
        return list(ids)

    # -- augmentation (optional) ---------------------------------------------------------------
    def symmetries(self) -> tuple[Symmetry, ...]:
        """The exact symmetries of the grammar (:class:`Symmetry`), without the identity, for the
        augmented streams of :mod:`plad.learn.augment`. Default: none."""
        return ()

    def edits(self) -> Mapping[str, Edit]:
        """Program edits of the domain's own for :mod:`plad.learn.augment`, by name; one named like a
        generic edit (``jitter``, ``drop``, ``graft``, which use :attr:`rewrite`) replaces it. Default: none."""
        return _NONE_EDITS

    # -- floor baseline (optional) ------------------------------------------------------------
    #: what :meth:`floor` infers, for the results table, e.g. ``"one box"``; "": the domain has no floor
    floor_name: str = ""

    def floor(self, targets: np.ndarray) -> list[list[int]]:
        """Floor baseline: for each target (bool (N, *shape)) the best program of a trivial family
        (e.g. one primitive), found without any network. Every number of the table should beat it.

        Only called when :attr:`floor_name` is set; the default offers none.
        """
        raise NotImplementedError(f"domain {self.name} has no floor baseline")

    #: the token kind (:attr:`plad.domains.grammar.Token.kind`) whose count is a program's complexity, the
    #: structural size the synthetic sampler stratifies by and the pretraining curriculum orders by
    #: (primitives of CSG, cuboids of ShapeAssembly); None: the domain offers no complexity
    complexity_kind: str | None = None

    def complexity(self, programs: np.ndarray) -> np.ndarray:
        """Complexity of -1-padded token rows (N, L): (N,) int, the number of :attr:`complexity_kind` tokens.

        Raises ``ValueError`` if the domain offers no complexity.
        """
        if self.complexity_kind is None:
            raise ValueError(f"domain {self.name} defines no program complexity (complexity_kind)")
        kinds = np.array([t.kind == self.complexity_kind for t in self.tokens.tokens] + [False])
        programs = np.asarray(programs)
        return kinds[np.where(programs >= 0, programs, len(kinds) - 1)].sum(1).astype(np.int64)

    # -- real data -----------------------------------------------------------------
    @property
    @abc.abstractmethod
    def targets(self) -> TargetSource:
        """Where the real target shapes come from (a dataset's source, shared by the domains on it).

        The ``prepare`` stage prepares each source once and writes its splits
        as ``<domain>.npz`` for every domain on it; the shapes must have :attr:`shape`.
        """

    def target_data(self, split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
        """Real target shapes of a split (``train``/``val``/``test``) from the data directory: bool (N, *shape)."""
        return self.targets.load(split, data_dir)

    # -- reinforcement learning --------------------------------------------------------------------
    @abc.abstractmethod
    def reward(self, values: torch.Tensor) -> torch.Tensor:
        """The RL reward in [0, 1] of metric values (N,) of sampled programs against their targets."""

    # -- command line (optional) -------------------------------------------------------------
    def execute_text(self, text: str, output: str | os.PathLike | None) -> str:
        """``plad execute``: run program text and write the shape to ``output`` (format by suffix).

        Returns what to show the user: a short summary, or the shape itself
        when there is no ``output``. Raises :class:`ProgramError` for a bad
        program, ``ValueError`` for an output type the domain cannot write.
        Default: token programs, written by :func:`save_grid`; without ``output``
        a 2D shape is drawn as text rows ('#' inside) above the program.
        """
        ids = self.parse(text)
        grid = self.execute(torch.tensor([ids]))[0].cpu().numpy()
        if output is not None:
            save_grid(grid, Path(output))
            return self.format(ids)
        if grid.ndim == 2:
            return "\n".join("".join("#" if v else "." for v in row) for row in grid) + "\n" + self.format(ids)
        return f"{self.format(ids)}: {int(grid.sum())} of {grid.size} cells occupied"

    #: formats of a program's files in other tools, by suffix (e.g. ``("svg",)``, ``("ply", "scad")``): what
    #: ``plad export`` writes and what ``plad infer`` writes beside each program (:meth:`export_files`);
    #: default: none
    export_formats: tuple[str, ...] = ()

    def write_export(self, ids: Sequence[int], fmt: str, path: Path) -> bool:
        """Write the valid program ``ids`` in format ``fmt`` (one of :attr:`export_formats`) to ``path``.

        Returns False when the program has nothing to write in that format (e.g. no surface for a mesh).
        Raises ``ValueError`` for a format the domain does not offer (the default offers none).
        """
        raise ValueError(self._unknown_format(fmt))

    def _unknown_format(self, fmt: str) -> str:
        known = ", ".join(self.export_formats) or "none"
        return f"unknown export format {fmt!r} for {self.name}; known: {known}"

    def export_program(self, text: str, fmt: str, path: Path) -> bool:
        """``plad export``: program text -> a file of format ``fmt`` at ``path`` (:meth:`write_export`).

        Raises :class:`ProgramError` for a bad program, ``ValueError`` for an unknown format.
        """
        if fmt not in self.export_formats:
            raise ValueError(self._unknown_format(fmt))
        return self.write_export(self.parse(text), fmt, Path(path))

    def export_text(self, text: str, fmt: str) -> bytes:
        """The bytes of :meth:`export_program`'s file (empty when there is nothing to write)."""
        import tempfile

        with tempfile.TemporaryDirectory(prefix="plad-export-") as tmp:
            path = Path(tmp) / f"program.{fmt}"
            return path.read_bytes() if self.export_program(text, fmt, path) else b""

    # -- outputs of inferred programs ------------------------------------------------------------
    def export_files(self, ids: Sequence[int], stem: Path) -> list[Path]:
        """Write the valid program ``ids`` in every format of :attr:`export_formats`, named ``stem`` plus the
        format's suffix (e.g. ``.svg``); return the paths written."""
        out = []
        for fmt in self.export_formats:
            path = Path(f"{stem}.{fmt}")
            if self.write_export(ids, fmt, path):
                out.append(path)
        return out


def save_grid(grid: np.ndarray, path: Path) -> None:
    """Write one executed shape: ``.npy`` (bool array), or for a 2D grid ``.png`` (8-bit gray, 255 inside),
    atomically (:func:`plad.fsutil.atomic_write`: a failure is a one-line ``WriteError`` and the old file stays).

    Raises ``ValueError`` naming the file for any other suffix.
    """
    from plad.data.pictures import save_npy, save_png

    suffix = path.suffix.lower()
    if suffix == ".npy":
        save_npy(grid.astype(bool), path)
    elif suffix == ".png" and grid.ndim == 2:
        save_png(grid.astype(np.uint8) * 255, path)
    else:
        allowed = ".png or .npy" if grid.ndim == 2 else ".npy"
        raise ValueError(f"{path}: unsupported output type {suffix or '(none)'!r}; use {allowed}")


def pad_programs(programs: Sequence[Sequence[int]], pad: int = 0,
                 device: str | torch.device = "cpu") -> torch.Tensor:
    """(B, L) long tensor of right-padded token ids (padding is ignored by executors)."""
    L = max((len(p) for p in programs), default=1)
    out = torch.full((len(programs), max(L, 1)), pad, dtype=torch.long)
    for i, p in enumerate(programs):
        if len(p):
            out[i, : len(p)] = torch.as_tensor(list(p), dtype=torch.long)
    return out.to(device)


def split_padding(programs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """-1-padded token rows (N, L) -> (rows with padding replaced by 0, lengths (N,)).

    Programs are stored -1-padded on disk; executors and the model take
    0-padded rows plus lengths.
    """
    return programs.clamp(min=0), (programs >= 0).sum(1)


__all__ = ["Domain", "Edit", "ProgramError", "Symmetry", "pad_programs", "save_grid", "split_padding"]
