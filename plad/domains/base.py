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
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from plad.data.files import TargetSource
from plad.domains.grammar import ProgramError, TokenTable
from plad.metrics import Metric

_NONE: Mapping[str, float] = MappingProxyType({})


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
    """Write one executed shape: ``.npy`` (bool array), or for a 2D grid ``.png`` (8-bit gray, 255 inside).

    Raises ``ValueError`` naming the file for any other suffix.
    """
    suffix = path.suffix.lower()
    if suffix == ".npy":
        np.save(path, grid.astype(bool))
    elif suffix == ".png" and grid.ndim == 2:
        from PIL import Image

        Image.fromarray(grid.astype(np.uint8) * 255, mode="L").save(path)
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


__all__ = ["Domain", "ProgramError", "pad_programs", "save_grid", "split_padding"]
