"""3D CSG domain: prefix programs of cuboids and ellipsoids with union/inter/diff on 32^3 voxels.

Modules: :mod:`.tokens` (vocabulary, grammar, text form), :mod:`.executor`
(batched bit-packed voxel executor), :mod:`.sampler` (synthetic programs),
:mod:`.export` (mesh, views, OpenSCAD).

Executed shapes are bool (B, 32, 32, 32) indexed [x, y, z], voxel (i, j, k)
centered at (i, j, k) in the parameters' index units. The real target shapes
are the PartNet shapes voxelized at 32^3 on the same grid and indexing
(:mod:`plad.data.datasets.partnet`).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from plad.data.files import TargetSource
from plad.domains.base import Domain
from plad.domains.csg3d.executor import Executor
from plad.domains.csg3d.tokens import RES, format_program, parse, token_table
from plad.domains.grammar import TokenTable
from plad.metrics import IOU, Metric


class CSG3D(Domain):
    name = "csg3d"
    shape = (RES, RES, RES)
    #: complexity: the number of primitives, what the sampler stratifies by
    complexity_kind = "primitive"
    title = "3D CSG"
    # IoU shown in percent, as in the paper
    display_scale, display_digits = 100.0, 1
    #: Table 1 of the paper: test IoU x 100, beam 10
    paper_table = {"sp": 41.0, "rl": 53.4, "ws": 67.4, "st": 67.3, "lest": 69.8, "lest_st": 70.8, "lest_st_ws": 74.3}

    @property
    def metric(self) -> Metric:  # type: ignore[override]
        return IOU

    @property
    def tokens(self) -> TokenTable:
        return token_table()

    @cached_property
    def executor(self) -> Executor:
        return Executor(self.tokens)

    @cached_property
    def rewrite(self):  # type: ignore[override]
        """Search support: PO over parameters, pruning of the prefix tree, boxes from the residual."""
        from plad.domains.csg3d.rewrite import CSG3DRewrite

        return CSG3DRewrite(self)

    def parse(self, text: str) -> list[int]:
        return parse(text)

    def format(self, ids: Sequence[int]) -> str:
        return format_program(ids)

    def execute(self, programs: torch.Tensor) -> torch.Tensor:
        """(B, L) token ids -> (B, 32, 32, 32) bool [x, y, z] on the programs' device."""
        return self.executor(programs)

    def sample(self, n: int, generator: np.random.Generator) -> list[list[int]]:
        from plad.domains.csg3d.sampler import sample_programs

        return sample_programs(self.executor, n, generator)

    def samplers(self):
        """The paper's sampler, and ``"parts"`` (beyond the paper): furniture-like unions of plates,
        sticks and blocks with mirror twins (:func:`.sampler.sample_parts_programs`)."""
        from plad.domains.csg3d.sampler import sample_parts_programs

        return {**super().samplers(), "parts": lambda n, generator: sample_parts_programs(self.executor, n, generator)}

    def canonical(self, ids: Sequence[int]) -> list[int]:
        """Cuboid and ellipsoid parameters snapped to one representative of the ones drawing the same voxels,
        union/inter operands ordered (:mod:`.canonical`)."""
        from plad.domains.csg3d.canonical import canonical_program

        return canonical_program(ids)

    def symmetries(self):
        """Quarter turns about the vertical y axis and mirrors through vertical planes, all exact
        (:mod:`.symmetry`)."""
        from plad.domains.csg3d.symmetry import symmetries

        return symmetries()

    floor_name = "one box"

    def floor(self, targets: np.ndarray) -> list[list[int]]:
        """One cuboid per target: the tightest axis-aligned box around it (:func:`.canonical.one_box`)."""
        from plad.domains.csg3d.canonical import one_box

        return one_box(targets)

    @property
    def targets(self) -> TargetSource:
        """The PartNet shapes (executed ShapeAssembly programs), voxelized at 32^3."""
        from plad.data.datasets.partnet.dataset import TARGETS

        return TARGETS

    def reward(self, values: torch.Tensor) -> torch.Tensor:
        """The IoU itself (already in [0, 1])."""
        return values.clamp(0, 1)

    # ---- command line -------------------------------------------------------------------
    def execute_text(self, text: str, output: str | os.PathLike | None) -> str:
        """``plad execute csg3d``: program text -> file by suffix.

        ``.npy`` the 32^3 bool grid [x, y, z], ``.ply``/``.obj`` a marching-cubes
        mesh of it (voxel index units), ``.png`` three orthographic views.
        Returns a one-line summary.
        """
        ids = self.parse(text)
        grid = self.execute(torch.tensor([ids]))[0].numpy()
        if output is not None:
            from plad.domains.csg3d import export

            path = Path(output)
            suffix = path.suffix.lower()
            if suffix == ".npy":
                from plad.data.pictures import save_npy

                save_npy(grid, path)
            elif suffix in (".ply", ".obj"):
                export.save_mesh(grid, path)
            elif suffix == ".png":
                export.save_views(grid, path, title=None)
            else:
                raise ValueError(f"{path}: unsupported output type {suffix or '(none)'!r}; "
                                 f"use .npy, .ply, .obj or .png")
        return f"{self.format(ids)}: {int(grid.sum())} of {RES ** 3} voxels occupied"

    #: a marching-cubes mesh of the execution (``ply``) and an equivalent OpenSCAD file (``scad``)
    export_formats = ("ply", "scad")

    def write_export(self, ids: Sequence[int], fmt: str, path: Path) -> bool:
        """``scad``: an equivalent OpenSCAD file; ``ply``: a marching-cubes mesh of the execution (False, nothing
        written, when the program executes to an empty grid: it has no surface)."""
        from plad.domains.csg3d.export import save_mesh, to_scad
        from plad.fsutil import atomic_write_text

        if fmt == "scad":
            atomic_write_text(path, to_scad(ids))
            return True
        if fmt != "ply":
            raise ValueError(self._unknown_format(fmt))
        grid = self.execute(torch.tensor([list(ids)]))[0].numpy()
        if not grid.any():
            return False
        save_mesh(grid, path)
        return True


__all__ = ["CSG3D"]
