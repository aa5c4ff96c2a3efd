"""ShapeAssembly domain: PLAD's discretized, non-hierarchical ShapeAssembly on 32^3 voxels.

Modules: :mod:`.tokens` (the discretized token language), :mod:`.sampler`
(synthetic programs), :mod:`.export` (mesh and PNG). Token programs are
turned into statements of the full hierarchical language and run by its
executor and voxelizer, which live with the PartNet dataset
(:mod:`plad.data.datasets.partnet`) because they define its shapes; the real
target shapes are those.

Executed shapes are bool (B, 32, 32, 32) indexed [x, y, z] on the grid of
the real data (voxel centers ``(i+.5)/32 - .5``, docs/shapeassembly.md, with the same
0.55-voxel minimum half-extent). A token program's bbox is ``1 x h/32 x 1``
centered at the origin, i.e. already in that centered unit cube, so it is not
renormalized. A program whose execution fails numerically (a cuboid frame
becomes singular) executes to the empty shape.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from plad.data.datasets.partnet.execute import ExecutionError
from plad.data.datasets.partnet.voxels import RES, voxelize_batch
from plad.data.files import TargetSource
from plad.domains.base import Domain
from plad.domains.grammar import ProgramError, TokenTable
from plad.domains.shapeassembly.cuboids import token_cuboids
from plad.domains.shapeassembly.tokens import format_program, parse, token_table
from plad.metrics import IOU, Metric


class ShapeAssembly(Domain):
    name = "shapeassembly"
    shape = (RES, RES, RES)
    #: complexity: the number of cuboids (parts), what the sampler stratifies by
    complexity_kind = "cuboid"
    title = "ShapeAssembly"
    # IoU shown in percent, as in the paper
    display_scale, display_digits = 100.0, 1
    #: Table 1 of the paper: test IoU x 100, beam 10
    paper_table = {"sp": 37.6, "rl": 50.8, "ws": 57.2, "st": 61.3, "lest": 56.5, "lest_st": 66.0, "lest_st_ws": 66.4}

    @property
    def metric(self) -> Metric:  # type: ignore[override]
        return IOU

    @property
    def tokens(self) -> TokenTable:
        return token_table()

    @cached_property
    def _end(self) -> int:
        return self.tokens.index("END")

    @cached_property
    def rewrite(self):  # type: ignore[override]
        """Search support: PO over the discretized arguments, parts placed where targets are missed."""
        from plad.domains.shapeassembly.rewrite import ShapeAssemblyRewrite

        return ShapeAssemblyRewrite(self)

    def parse(self, text: str) -> list[int]:
        """Token text. A program of the full language (which ``plad execute`` and ``plad export`` run) has no
        token form to rewrite: it is refused with the way to a token program of its shape."""
        if _full_language(text):
            raise ProgramError("a program of the full ShapeAssembly language, which `plad execute` and `plad "
                               "export` run; refine and inference work on the domain's token programs (docs/"
                               "shapeassembly.md): search or infer one for its shape instead, e.g. `plad execute "
                               "shapeassembly PROGRAM -o shape.npy` then `plad search shapeassembly shape.npy`",
                               position=0)
        return parse(text)

    def format(self, ids: Sequence[int]) -> str:
        return format_program(ids)

    def run_batch(self, programs) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Execute token programs (list of id lists, or (B, L) tensor rows).

        Returns grids (B, 32, 32, 32) bool (cpu), unique (N,) long voxels owned
        alone by each of the N cuboids of the batch, owner (N,) long program
        index of each cuboid, ok (B,) bool execution succeeded.
        """
        rows = programs.tolist() if isinstance(programs, torch.Tensor) else programs
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

    def execute(self, programs: torch.Tensor) -> torch.Tensor:
        """(B, L) token ids -> (B, 32, 32, 32) bool [x, y, z] on the programs' device."""
        return self.run_batch(programs.cpu())[0].to(programs.device)

    def sample(self, n: int, generator: np.random.Generator) -> list[list[int]]:
        from plad.domains.shapeassembly.sampler import sample_programs

        return sample_programs(self, n, generator)

    def samplers(self):
        """The paper's sampler, and ``"inside"`` (beyond the paper): every part kept inside the bbox, as
        PartNet's are, and most bboxes full height, as most voxelized PartNet shapes are
        (:func:`.sampler.sample_programs`)."""
        from plad.domains.shapeassembly.sampler import sample_programs

        return {**super().samplers(),
                "inside": lambda n, generator: sample_programs(self, n, generator, inside=True)}

    # canonical(): the default, the program itself. No choice of this language is free: the two Attaches of a
    # part run in order (the first translates, the second scales and turns), Squeeze's two targets play
    # different roles (the named face against the first), a Reflect or Translate copy re-solves the moves in
    # order, and every number moves or sizes a cuboid and so places what is attached to it: numbers that
    # draw the same voxels do so only in context (docs/shapeassembly.md, "The discretized language of the domain").

    def symmetries(self):
        """The mirrors through the bbox's vertical centre planes and their composition, a half turn
        (:mod:`.symmetry`); exact up to float32 rounding at voxel boundaries."""
        from plad.domains.shapeassembly.symmetry import symmetries

        return symmetries()

    def edits(self):
        """Grafting a whole part of another program (:mod:`.edits`): the language has no expression tree."""
        from plad.domains.shapeassembly.edits import graft

        return {"graft": graft}

    floor_name = "one box"

    def floor(self, targets: np.ndarray) -> list[list[int]]:
        """One cuboid per target, centred and sized to its tight box (:func:`.floor.one_box`)."""
        from plad.domains.shapeassembly.floor import one_box

        return one_box(self, targets)

    @property
    def targets(self) -> TargetSource:
        """The PartNet shapes, the programs this language was discretized from, voxelized at 32^3."""
        from plad.data.datasets.partnet.dataset import TARGETS

        return TARGETS

    def reward(self, values: torch.Tensor) -> torch.Tensor:
        """The IoU itself (already in [0, 1])."""
        return values.clamp(0, 1)

    # ---- command line -------------------------------------------------------------------
    def execute_text(self, text: str, output: str | os.PathLike | None) -> str:
        """``plad execute shapeassembly``: full-language text or token text -> file.

        Output by suffix: ``.npy`` the 32^3 bool grid [x, y, z] (full-language
        shapes normalized by their tight bounds, docs/shapeassembly.md), ``.ply``/``.obj``
        a mesh of the cuboids, ``.png`` three orthographic views. Returns a
        one-line summary.
        """
        from plad.data.datasets.partnet.execute import run_text
        from plad.data.datasets.partnet.voxels import voxelize

        if _full_language(text):
            cuboids = run_text(text)
            grid = voxelize(cuboids)
            kind = "full-language program"
        else:
            ids = self.parse(text)
            cuboids = token_cuboids(ids)
            grid = voxelize(cuboids, normalized=True)
            kind = f"token program {self.format(ids)!r}"
        if output is not None:
            path = Path(output)
            suffix = path.suffix.lower()
            if suffix == ".npy":
                from plad.data.pictures import save_npy

                save_npy(grid, path)
            elif suffix in (".ply", ".obj"):
                from plad.domains.shapeassembly.export import save_mesh

                save_mesh(cuboids, path)
            elif suffix == ".png":
                from plad.domains.shapeassembly.export import save_views

                save_views(cuboids, path)
            else:
                raise ValueError(f"{path}: unsupported output type {suffix or '(none)'!r}; "
                                 f"use .npy, .ply, .obj or .png")
        return f"{kind}: {len(cuboids)} cuboids, {int(grid.sum())} of {RES ** 3} voxels occupied"

    #: a mesh of the program's cuboids (the grid's centered unit-cube frame)
    export_formats = ("ply",)

    def write_export(self, ids: Sequence[int], fmt: str, path: Path) -> bool:
        """``ply``: a mesh of the program's cuboids (False, nothing written, when a singular frame makes the
        program execute to nothing)."""
        from plad.domains.shapeassembly.export import save_mesh

        if fmt != "ply":
            raise ValueError(self._unknown_format(fmt))
        try:
            save_mesh(token_cuboids(ids), path)
        except ExecutionError:      # a singular frame: the program executes to nothing
            return False
        return True

    def export_program(self, text: str, fmt: str, path: Path) -> bool:
        """Token programs as every domain's; a program of the full language too (as ``plad execute`` runs it)."""
        if not _full_language(text):
            return super().export_program(text, fmt, path)
        from plad.data.datasets.partnet.execute import run_text
        from plad.domains.shapeassembly.export import save_mesh

        if fmt not in self.export_formats:
            raise ValueError(self._unknown_format(fmt))
        save_mesh(run_text(text), path)
        return True


def _full_language(text: str) -> bool:
    """Whether ``text`` is a program of the full hierarchical language (``Assembly`` blocks, ``Cuboid(...)``)
    rather than of the domain's token language."""
    return "Assembly" in text or "Cuboid(" in text


__all__ = ["ShapeAssembly", "token_cuboids"]
