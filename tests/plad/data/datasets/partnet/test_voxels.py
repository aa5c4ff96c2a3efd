"""voxelize_batch: the batched voxelizer gives exactly the original per-cuboid voxelizer's grids and unique
counts (tests/reference/shapeassembly_v0.py, the frozen original) on every kind of input, with its counts as
matrix products and in the compiled kernels (plad.data.datasets.partnet.voxels_compiled)."""
import importlib

import numpy as np
import pytest
import torch

from plad.data.datasets.partnet.voxels import MIN_HALF, normalization, normalize, voxelize_batch
from plad.domains import get_domain
from tests.grammar import masked_rollouts
from tests.reference import shapeassembly_v0 as v0

voxels = importlib.import_module("plad.data.datasets.partnet.voxels")


@pytest.fixture(autouse=True, params=[False, True], ids=["products", "compiled"])
def compiled(request, monkeypatch):
    """Every test on both paths of the counts (the default picks by plad.jit's rule)."""
    if request.param:
        from plad.data.datasets.partnet import voxels_compiled

        assert voxels_compiled.available()
    monkeypatch.setattr(voxels, "_COMPILED", request.param)


def assert_same(cuboids: np.ndarray, owner: np.ndarray, batch: int, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    c, o = torch.from_numpy(cuboids), torch.from_numpy(owner.astype(np.int64))
    with np.errstate(invalid="ignore", divide="ignore"):
        want = v0.voxelize_batch(c, o, batch, **kw)
        got = voxelize_batch(c, o, batch, **kw)
    assert got[0].dtype == want[0].dtype == torch.bool and got[1].dtype == want[1].dtype == torch.long
    assert got[0].shape == want[0].shape and torch.equal(got[0], want[0]), kw
    assert torch.equal(got[1], want[1]), kw
    return got


def random_cuboids(rng: np.random.Generator, n: int) -> np.ndarray:
    """Cuboids of every kind: grid-aligned (axes permuted, flipped, scaled), rotated, nearly aligned, with a zero
    axis, zero and negative dims, partly or wholly outside the grid, centres on voxel centres and boundaries."""
    c = np.zeros((n, 15))
    c[:, 0:3] = rng.uniform(-0.8, 0.8, (n, 3))
    c[:, 12:15] = rng.uniform(-0.3, 0.7, (n, 3)) * (rng.random((n, 3)) > 0.1)
    for i in range(n):
        r = rng.random()
        if r < 0.6:
            axes = np.eye(3)[rng.permutation(3)] * rng.choice([-1, 1], (3, 1)) * rng.uniform(0.1, 3, (3, 1))
        elif r < 0.9:
            axes, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        elif r < 0.95:
            axes = np.eye(3)
            axes[0, 1] = 1e-9
        else:
            axes = np.eye(3)
            axes[rng.integers(3)] = 0                       # a zero axis: NaN after normalizing
        c[i, 3:12] = axes.reshape(-1)
    snap = rng.random(n) < 0.3                               # knife edges: centres on the 1/64 lattice
    c[snap, 0:3] = np.round(c[snap, 0:3] * 64) / 64
    return c


@pytest.mark.parametrize("seed", range(6))
def test_random_cuboids_as_the_original(seed):
    rng = np.random.default_rng(seed)
    for _ in range(4):
        n, batch = int(rng.integers(0, 150)), int(rng.integers(1, 60))
        c = random_cuboids(rng, n)
        owner = rng.integers(0, batch, n) if seed % 2 else np.sort(rng.integers(0, batch, n))
        for dtype in (np.float64, np.float32):
            assert_same(c.astype(dtype), owner, batch)
            assert_same(c.astype(dtype), owner, batch, min_half=0.0)
            assert_same(c.astype(dtype), owner, batch, res=16)


def test_empty_inputs_as_the_original():
    grids, unique = assert_same(np.zeros((0, 15), np.float32), np.zeros(0, np.int64), 3)
    assert grids.shape == (3, 32, 32, 32) and not grids.any() and unique.shape == (0,)
    assert_same(np.zeros((0, 15), np.float32), np.zeros(0, np.int64), 0)


def test_many_shapes_past_one_chunk():
    # more shapes than one chunk holds, shapes without cuboids among them, one shape with many cuboids
    rng = np.random.default_rng(7)
    c = random_cuboids(rng, 600)
    owner = np.where(rng.random(600) < 0.1, 5, rng.integers(0, 300, 600))
    assert_same(c, owner, 310)


def test_token_programs_as_the_original():
    """Random grammar-valid programs (rotated cuboids and failed executions among them), in batches as the
    domain's run_batch sends them."""
    domain = get_domain("shapeassembly")
    programs = masked_rollouts(domain, 300, seed=3)
    cubs, owners = [], []
    for b, ids in enumerate(programs):
        try:
            c = v0.token_cuboids(ids)
        except v0.ExecutionError:
            c = np.zeros((0, 15), np.float32)
        cubs.append(c)
        owners.append(np.full(len(c), b))
    cuboids, owner = np.concatenate(cubs), np.concatenate(owners)
    axes = cuboids[:, 3:12].reshape(-1, 3, 3)
    assert (np.count_nonzero(axes, axis=(1, 2)) > 3).any(), "some cuboids should be rotated"
    assert_same(cuboids, owner, len(programs))
    assert_same(cuboids, owner, len(programs), min_half=0.0)


def test_partnet_shapes_as_the_original(fixtures_dir):
    """The 120 real shapes of the fixture, normalized as the dataset voxelizes them, with and without the
    0.55-voxel minimum."""
    from plad.data.datasets.partnet.execute import run_text

    fixture = np.load(fixtures_dir / "shapeassembly_reference.npz")
    cubs = [run_text(str(t)) for t in fixture["program_text"]]
    cubs = [normalize(c, *normalization(c)) for c in cubs]
    owner = np.concatenate([np.full(len(c), b) for b, c in enumerate(cubs)])
    for min_half in (MIN_HALF, 0.0):
        assert_same(np.concatenate(cubs), owner, len(cubs), min_half=min_half)
