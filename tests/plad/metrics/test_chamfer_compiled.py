"""The compiled CPU Chamfer (plad.metrics.chamfer_compiled) gives the tensor path's numbers bit for bit.

Here every call is compiled (``chamfer._COMPILED`` True); by default a process compiles once it has earned it
(plad.jit, tests/plad/test_jit.py).

Its edges against the tensor Canny (itself tested against OpenCV), its CD and chamfer_against against the tensor
path with the compiled kernels switched off (``chamfer._COMPILED``), on every kind of image of test_chamfer, at
64 x 64 and at other sizes, degenerate pairs included.
"""
from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from plad.metrics import chamfer_compiled
from tests.binary_images import every_image, random_images

chamfer_module = importlib.import_module("plad.metrics.chamfer")


def test_numba_is_there():
    # a dependency of the project: without it the compiled path would silently never run
    assert chamfer_compiled.available()


@pytest.fixture(autouse=True)
def always_compiled(monkeypatch):
    """Every call here compiled (the default waits until a process has earned it, plad.jit)."""
    monkeypatch.setattr(chamfer_module, "_COMPILED", True)


def _tensor_path(monkeypatch, fn, *args):
    with monkeypatch.context() as m:
        m.setattr(chamfer_module, "_COMPILED", False)
        return fn(*args)


def _images(h: int, w: int, n: int, seed: int) -> np.ndarray:
    """n images of every kind, or every image of a tiny size (its 2^(h w) images, at most n)."""
    if h * w <= 12:
        return every_image(h, w)[:n]
    return random_images(n, seed=seed, h=h, w=w)


def _pairs(h: int, w: int, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    images = _images(h, w, n, seed)
    n = len(images)
    rng = np.random.default_rng(seed)
    other = images[rng.permutation(n)]
    shifted = np.roll(images, (1, -2), axis=(1, 2))
    near = np.where(rng.random((n, 1, 1)) < 0.5, other, shifted)
    return torch.from_numpy(images), torch.from_numpy(near)


def test_pack_rows_puts_pixel_x_on_bit_x():
    img = np.zeros((2, 3, 64), dtype=bool)
    img[0, 0, 0] = img[0, 1, 63] = img[1, 2, 5] = img[1, 2, 6] = True
    rows = chamfer_compiled.pack_rows(img)
    assert rows.dtype == np.uint64 and rows.shape == (2, 3)
    assert rows.tolist() == [[1, 1 << 63, 0], [0, 0, (1 << 5) | (1 << 6)]]
    narrow = chamfer_compiled.pack_rows(img[:, :, :7])
    assert narrow.tolist() == [[1, 0, 0], [0, 0, (1 << 5) | (1 << 6)]]
    with pytest.raises(ValueError, match="at most 64 pixels"):
        chamfer_compiled.pack_rows(np.zeros((1, 2, 65), dtype=bool))


@pytest.mark.parametrize("shape", [(64, 64), (64, 50), (20, 64), (17, 23), (1, 10), (10, 1), (3, 3), (3, 4)])
def test_edges_equal_the_tensor_canny(shape):
    images = _images(*shape, n=4096, seed=11)
    rows = chamfer_compiled.pack_rows(images)
    out = np.zeros_like(rows)
    chamfer_compiled.edges_of(rows, shape[1], out)
    expected = chamfer_module.canny_binary(torch.from_numpy(images)).numpy()
    assert np.array_equal(out, chamfer_compiled.pack_rows(expected))


@pytest.mark.parametrize("shape", [(64, 64), (64, 50), (20, 64), (17, 23), (1, 10), (3, 3), (3, 4)])
def test_chamfer_equals_the_tensor_path_bit_for_bit(shape, monkeypatch):
    pred, target = _pairs(*shape, n=600, seed=3)
    ours = chamfer_module.chamfer(pred, target)
    theirs = _tensor_path(monkeypatch, chamfer_module.chamfer, pred, target)
    assert ours.dtype == torch.float64 and ours.shape == pred.shape[:1]
    assert torch.equal(ours, theirs)
    if shape == (64, 64):  # the pairs hold both kinds: degenerate and ordinary
        assert (ours == chamfer_module.PENALTY).sum() >= 4 and (ours < chamfer_module.PENALTY).sum() > 300


def test_chamfer_keeps_leading_dims(monkeypatch):
    pred, target = _pairs(64, 64, n=60, seed=5)
    ours = chamfer_module.chamfer(pred.view(3, 4, 5, 64, 64), target.view(3, 4, 5, 64, 64))
    assert ours.shape == (3, 4, 5)
    assert torch.equal(ours.flatten(), _tensor_path(monkeypatch, chamfer_module.chamfer, pred, target))


@pytest.mark.parametrize("shape", [(64, 64), (30, 40)])
def test_chamfer_against_equals_the_tensor_path(shape, monkeypatch):
    images = random_images(300, seed=7, h=shape[0], w=shape[1])
    rng = np.random.default_rng(8)
    n, k = 29, 6
    targets = torch.from_numpy(images[rng.integers(0, len(images), n)])
    cands = torch.from_numpy(images[rng.integers(0, len(images), (n, k))])
    cands[:, 0] = targets  # the target itself among the candidates
    cands[:, 1] = torch.roll(targets, 1, dims=2)
    features = chamfer_module.TargetFeatures.of(targets)
    ours = chamfer_module.chamfer_against(cands, features)
    again = chamfer_module.chamfer_against(cands, features)  # the packed target rows reused
    theirs = _tensor_path(monkeypatch, chamfer_module.chamfer_against, cands, features)
    assert ours.shape == (n, k) and torch.equal(ours, theirs) and torch.equal(again, ours)
    assert torch.equal(chamfer_module.chamfer_against(cands[:, 2], features), theirs[:, 2])


def test_fixture_values_unchanged(fixtures_dir, monkeypatch):
    data = np.load(fixtures_dir / "csgnet_chamfer_reference.npz")
    pred, target = torch.from_numpy(data["pred"]), torch.from_numpy(data["target"])
    ours = chamfer_module.chamfer(pred, target)
    assert torch.equal(ours, _tensor_path(monkeypatch, chamfer_module.chamfer, pred, target))
    assert np.abs(ours.numpy() - data["chamfer"]).max() <= 1e-4


def test_more_than_one_thread_gives_the_same_numbers(monkeypatch):
    pred, target = _pairs(64, 64, n=3000, seed=9)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = chamfer_module.chamfer(pred, target)
        torch.set_num_threads(2)
        two = chamfer_module.chamfer(pred, target)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)
