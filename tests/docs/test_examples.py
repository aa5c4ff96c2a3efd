"""examples/: every file is an input `plad infer` reads, the .npy files are the executions of the
programs examples/README.md names, and every examples/ path the README and docs/ use exists."""
from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from plad.data.inputs import read_inputs
from plad.domains import domain_names, get_domain
from tests.conftest import REPO_ROOT as REPO

EXAMPLES = REPO / "examples"


@pytest.mark.parametrize("name", domain_names())
def test_every_domain_has_examples_that_infer_reads(name):
    domain = get_domain(name)
    items = read_inputs([str(EXAMPLES / name)], tuple(domain.shape))
    assert len(items) >= 2
    for it in items:
        assert it.error is None, f"{it.source}: {it.error}"
        assert it.shape.shape == tuple(domain.shape) and it.shape.any()


def test_the_npy_examples_are_the_executed_programs():
    table = (EXAMPLES / "README.md").read_text()
    csg3d = get_domain("csg3d")
    for stem in ("block", "stool"):
        program = re.search(rf"`plad execute csg3d \"([^\"]+)\" -o {stem}\.npy`", table).group(1)
        want = csg3d.execute(torch.tensor([csg3d.parse(program)]))[0].numpy()
        assert np.array_equal(np.load(EXAMPLES / "csg3d" / f"{stem}.npy"), want), stem
    csg2d = get_domain("csg2d")
    for stem in ("gear", "house", "ring"):
        program = re.search(rf"`csg2d/{stem}\.png` \| [^|]+\| `([^`]+)`", table).group(1)
        want = csg2d.execute(torch.tensor([csg2d.parse(program)]))[0].numpy()
        from PIL import Image

        drawn = np.asarray(Image.open(EXAMPLES / "csg2d" / f"{stem}.png").convert("L")) < 128   # black inside
        assert drawn.shape == (256, 256) and np.array_equal(drawn[::4, ::4], want), stem      # 4x4 blocks


def test_the_shapeassembly_programs_execute_to_their_voxels(tmp_path):
    from plad.serve.cli import main

    for stem in ("chair", "table"):
        assert main(["execute", "shapeassembly", str(EXAMPLES / "shapeassembly" / f"{stem}.txt"),
                     "-o", str(tmp_path / f"{stem}.npy")]) == 0
        assert np.array_equal(np.load(tmp_path / f"{stem}.npy"), np.load(EXAMPLES / "shapeassembly" / f"{stem}.npy"))


def test_every_examples_path_in_the_readme_and_docs_exists():
    readme = (REPO / "README.md").read_text()
    assert re.search(r"examples/[\w./-]*\w", readme), "the README uses no example"
    texts = [readme, *(p.read_text() for p in sorted((REPO / "docs").glob("*.md")))]
    paths = {p for text in texts for p in re.findall(r"examples/[\w./-]*\w", text)}
    missing = sorted(p for p in paths if not (REPO / p).exists())
    assert not missing, missing
    # the ShapeAssembly commands run on a file the repository ships
    commands = [line for text in texts for line in text.splitlines() if line.startswith("plad execute shapeassembly")]
    assert commands, "no page shows `plad execute shapeassembly`"
    for line in commands:
        assert "examples/shapeassembly/" in line, line
