"""One reading of transparency and of files of several frames (issue 53, reproduction 8), fuzzed over random
drawings: a few stray transparent pixels on an opaque drawing never turn it into a filled square (they are
background, with a note); an opaque shape on a transparent background, or a cut-out in a sheet of one color, is
read from the alpha channel (with a note); an animated GIF or a multi-page TIFF is read from its first frame,
with a note. Each note says what was done."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from plad.data.inputs import read_file
from tests.conftest import REPO_ROOT

CANVAS = (64, 64)


def drawing(rng: np.random.Generator, size: int = 96) -> np.ndarray:
    """A random shape (bool (size, size)): a few rectangles and discs, away from the border."""
    yy, xx = np.mgrid[:size, :size]
    shape = np.zeros((size, size), bool)
    for _ in range(int(rng.integers(1, 4))):
        cy, cx = rng.integers(size // 4, 3 * size // 4, 2)
        r = int(rng.integers(6, size // 5))
        shape |= ((yy - cy) ** 2 + (xx - cx) ** 2 <= r * r) if rng.random() < 0.5 else \
            ((abs(yy - cy) <= r) & (abs(xx - cx) <= r // 2 + 2))
    return shape


def rgba(shape: np.ndarray, ink, paper, alpha: np.ndarray) -> np.ndarray:
    out = np.zeros((*shape.shape, 4), np.uint8)
    out[..., :3] = np.where(shape[..., None], np.array(ink, np.uint8), np.array(paper, np.uint8))
    out[..., 3] = alpha
    return out


def read(tmp_path, array, name="x.png", **save):
    path = tmp_path / name
    Image.fromarray(array).save(path, **save)
    (item,) = read_file(path, CANVAS)
    assert item.error is None, item.error
    return item


@pytest.mark.parametrize("seed", range(6))
def test_stray_transparent_pixels_on_an_opaque_drawing_are_background(tmp_path, seed):
    rng = np.random.default_rng(seed)
    shape = drawing(rng)
    opaque = np.full(shape.shape, 255, np.uint8)
    plain = read(tmp_path, rgba(shape, (0, 0, 0), (255, 255, 255), opaque), "plain.png")
    holes = opaque.copy()
    outside = np.argwhere(~shape)
    for r, c in outside[rng.choice(len(outside), int(rng.integers(1, 6)), replace=False)]:
        holes[r, c] = 0                              # transparent background pixels: the same shape
    item = read(tmp_path, rgba(shape, (0, 0, 0), (255, 255, 255), holes))
    assert np.array_equal(item.shape, plain.shape)  # never a filled square
    assert any("transparent pixel(s) as background" in n for n in item.notes), item.notes


@pytest.mark.parametrize("seed", range(6))
def test_a_shape_on_a_transparent_background_or_cut_out_of_a_sheet_is_the_alpha(tmp_path, seed):
    rng = np.random.default_rng(100 + seed)
    shape = drawing(rng)
    colors = rng.integers(0, 256, (*shape.shape, 3)).astype(np.uint8)     # a shape of many colors
    logo = np.concatenate([colors, np.where(shape, 255, 0).astype(np.uint8)[..., None]], -1)
    item = read(tmp_path, logo, "logo.png")
    reference = read(tmp_path, (~shape).astype(np.uint8) * 255, "ref.png")   # the same shape, black on white
    assert np.array_equal(item.shape, reference.shape)
    assert any("from the alpha channel: the opaque pixels" in n for n in item.notes), item.notes
    stencil = rgba(shape, (200, 200, 200), (200, 200, 200), np.where(shape, 0, 255).astype(np.uint8))
    item = read(tmp_path, stencil, "stencil.png")    # one color: the alpha is all there is
    assert np.array_equal(item.shape, reference.shape)
    assert any("from the alpha channel: the transparent pixels" in n for n in item.notes), item.notes


def test_the_gear_with_one_transparent_pixel_is_still_the_gear(tmp_path):
    gear = np.asarray(Image.open(REPO_ROOT / "examples/csg2d/gear.png").convert("RGBA")).copy()
    plain = read(tmp_path, gear, "gear.png")
    gear[0, 0, 3] = 0
    item = read(tmp_path, gear, "gear1.png")
    assert np.array_equal(item.shape, plain.shape) and item.shape.mean() < 0.5


@pytest.mark.parametrize("fmt", ["GIF", "TIFF"])
def test_a_file_of_several_frames_is_read_from_its_first_with_a_note(tmp_path, fmt):
    rng = np.random.default_rng(7)
    frames = [Image.fromarray((~drawing(rng)).astype(np.uint8) * 255) for _ in range(3)]
    path = tmp_path / f"anim.{fmt.lower()}"
    frames[0].save(path, format=fmt, save_all=True, append_images=frames[1:])
    frames[0].save(tmp_path / f"first.{fmt.lower()}", format=fmt)
    (item,) = read_file(path, CANVAS)
    (first,) = read_file(tmp_path / f"first.{fmt.lower()}", CANVAS)
    assert np.array_equal(item.shape, first.shape)
    assert "the file holds 3 frames (an animation or pages): read the first only" in item.notes
    assert not any("frames" in n for n in first.notes)
