"""Fixtures shared by the test files of plad/learn (the torchrun tests: test_distributed*.py)."""
from __future__ import annotations

import pytest

from plad.layout import Layout


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """The layout folder of a few synthetic 2D programs (``data/synthetic`` of a layout root)."""
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    root = tmp_path_factory.mktemp("synthetic")
    synthesize(SynthesizeConfig(domain="csg2d", train_programs=600, val_programs=32, seed=0), Layout(root))
    return Layout(root).synthetic_dir
