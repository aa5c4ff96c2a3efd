"""2D CSG domain (CSGNet's language on a 64 x 64 canvas)."""
from __future__ import annotations

import os
from functools import cached_property
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from plad.domains.base import Domain
from plad.domains.csg2d.executor import Executor
from plad.domains.csg2d.sampler import sample_programs
from plad.domains.csg2d.tokens import CANVAS, format_program, parse, token_table
from plad.grammar import TokenTable
from plad.metrics import Metric, chamfer_metric


class CSG2D(Domain):
    name = "csg2d"
    shape = (CANVAS, CANVAS)

    @cached_property
    def metric(self) -> Metric:  # type: ignore[override]
        return chamfer_metric()

    @property
    def tokens(self) -> TokenTable:
        return token_table()

    @cached_property
    def executor(self) -> Executor:
        return Executor(self.tokens)

    @cached_property
    def rewrite(self):  # type: ignore[override]
        """Search support: PO over draw tokens, pruning of the postfix tree, insertion at the root."""
        from plad.domains.csg2d.rewrite import CSG2DRewrite

        return CSG2DRewrite(self)

    def parse(self, text: str) -> list[int]:
        return parse(text)

    def format(self, ids: Sequence[int]) -> str:
        return format_program(ids)

    def execute(self, programs: torch.Tensor) -> torch.Tensor:
        return self.executor(programs)

    def sample(self, n: int, generator: np.random.Generator) -> list[list[int]]:
        return sample_programs(self.executor, n, generator)

    def target_data(self, split: str, data_dir: str | os.PathLike | None = None) -> np.ndarray:
        from plad.data import load_cad

        return load_cad(data_dir, split)

    def export_files(self, ids: Sequence[int], stem: Path) -> list[Path]:
        """``<stem>.svg``: the program's primitives as vector shapes, its operations as masks."""
        from plad.domains.csg2d.export import to_svg
        from plad.fsutil import atomic_write_text

        path = Path(f"{stem}.svg")
        atomic_write_text(path, to_svg(ids))
        return [path]
