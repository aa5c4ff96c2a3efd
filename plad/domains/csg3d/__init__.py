"""3D CSG domain: prefix programs of cuboids and ellipsoids with union/inter/diff on 32^3 voxels.

Modules: :mod:`.tokens` (vocabulary, grammar, text form), :mod:`.executor`
(batched bit-packed voxel executor), :mod:`.sampler` (synthetic programs).


Executed shapes are bool (B, 32, 32, 32) indexed [x, y, z], voxel (i, j, k)
centered at (i, j, k) in the parameters' index units. The real target shapes
are the same PartNet-derived 32^3 voxels as ShapeAssembly's (same grid and
indexing), read through :func:`plad.domains.shapeassembly.dataset.load_split`.
"""
from __future__ import annotations

import os
from functools import cached_property
from typing import Sequence

import numpy as np
import torch

from plad.domains.base import Domain
from plad.domains.csg3d.executor import Executor
from plad.domains.csg3d.tokens import RES, format_program, parse, token_table
from plad.grammar import TokenTable
from plad.metrics import IOU, Metric


class CSG3D(Domain):
    name = "csg3d"
    shape = (RES, RES, RES)

    @property
    def metric(self) -> Metric:  # type: ignore[override]
        return IOU

    @property
    def tokens(self) -> TokenTable:
        return token_table()

    @cached_property
    def executor(self) -> Executor:
        return Executor(self.tokens)

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

    def target_data(self, split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
        from plad.domains.shapeassembly.dataset import load_split

        return load_split(split, data_dir)


__all__ = ["CSG3D"]
