"""2D CSG domain (CSGNet's language on a 64 x 64 canvas)."""
from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from plad.data.files import TargetSource
from plad.domains.base import Domain
from plad.domains.csg2d.executor import Executor
from plad.domains.csg2d.sampler import sample_programs
from plad.domains.csg2d.tokens import CANVAS, format_program, parse, token_table
from plad.domains.grammar import TokenTable
from plad.metrics import Metric, chamfer_metric


class CSG2D(Domain):
    name = "csg2d"
    shape = (CANVAS, CANVAS)
    #: complexity: the number of draw tokens (primitives), what the sampler stratifies by
    complexity_kind = "draw"
    title = "2D CSG"
    # Chamfer distance in pixels, shown as it is
    display_scale, display_digits = 1.0, 3
    #: Table 1 of the paper: test Chamfer distance, beam 10
    paper_table = {"sp": 1.580, "rl": 1.097, "ws": 1.118, "st": 0.841, "lest": 0.976, "lest_st": 0.829,
                   "lest_st_ws": 0.811}
    #: the supplement: the same with P_BEST reset every round
    paper_per_round = {"st": 0.881, "lest": 1.011, "lest_st": 0.853, "lest_st_ws": 0.845}

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

    def canonical(self, ids: Sequence[int]) -> list[int]:
        """Operands of ``+`` and ``*`` in a fixed order (:mod:`.canonical`); every draw token draws its own bitmap."""
        from plad.domains.csg2d.canonical import canonical_program

        return canonical_program(ids)

    def symmetries(self):
        """The flips and quarter turns of the canvas the vocabulary can draw (:mod:`.symmetry`): ``flip_lr``
        for every program, the other six for programs without triangles (drawn apex-up only)."""
        from plad.domains.csg2d.symmetry import symmetries

        return symmetries()

    floor_name = "one primitive"

    def floor(self, targets: np.ndarray) -> list[list[int]]:
        """One draw token per target: the one with the best Chamfer distance (:func:`.canonical.one_primitive`)."""
        from plad.domains.csg2d.canonical import one_primitive

        draws = np.array([i for i, t in enumerate(self.tokens.tokens) if t.kind == "draw"])
        return one_primitive(targets, self.executor.bitmaps, draws)

    @property
    def targets(self) -> TargetSource:
        """CSGNet's CAD drawings."""
        from plad.data.datasets.cad import TARGETS

        return TARGETS

    def reward(self, values: torch.Tensor) -> torch.Tensor:
        """CSGNet's reward of a Chamfer distance d: ``clip(1 - d / diagonal, 0, 1) ** 20`` (canvas diagonal)."""
        diagonal = math.sqrt(sum(s * s for s in self.shape))
        return (1 - values / diagonal).clamp(0, 1) ** 20

    #: the program as an SVG drawing (its primitives as vector shapes, its operations as masks)
    export_formats = ("svg",)

    def write_export(self, ids: Sequence[int], fmt: str, path: Path) -> bool:
        """``svg``: the program's primitives as vector shapes, its operations as masks."""
        from plad.domains.csg2d.export import to_svg
        from plad.fsutil import atomic_write_text

        if fmt != "svg":
            raise ValueError(self._unknown_format(fmt))
        atomic_write_text(path, to_svg(ids))
        return True
