"""The cuboids of a token program: its statements run by the full language's executor.

Its own module so that the sampler (:mod:`.sampler`), which checks the cuboids of the programs it draws, and
the domain (the package) both use it without importing each other.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from plad.data.datasets.partnet.execute import execute_program
from plad.data.datasets.partnet.lang import Block, Program
from plad.domains.shapeassembly.tokens import to_statements


def _copy_name(parent: str, index: int | None) -> str:
    """PLAD's names for reflect / translate copies (never collide with cube0..cube9)."""
    return f"{parent}_ref" if index is None else f"{parent}_trans_{index}"


def token_cuboids(ids: Sequence[int]) -> np.ndarray:
    """Cuboids (n, 15) float32 of a valid token program (copies included), in the bbox frame.

    Raises :class:`~plad.data.datasets.partnet.execute.ExecutionError` if a
    frame becomes singular.
    """
    program = Program({"Program_0": Block("Program_0", to_statements(ids))}, "Program_0")
    return execute_program(program, copy_names=_copy_name)
