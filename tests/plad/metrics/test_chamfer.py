"""CSGNet's Chamfer distance: plad.metrics.chamfer against OpenCV and the fixture.

Canny must equal OpenCV bit for bit. The distance maps must equal the exact
3x3 chamfer distance (computed here by brute force) rounded to float32, which
OpenCV 5 matches up to its own float32 accumulation (a few ulps). The CD must
reproduce the reference fixture to 1e-4 and the per-pair OpenCV reference
(tests/reference/chamfer_cv.py) to 1e-5.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

cv2 = pytest.importorskip("cv2")

from plad.metrics.chamfer import (  # noqa: E402
    CANNY_TG22,
    PENALTY,
    STEP_DIAG,
    STEP_HV,
    TargetFeatures,
    canny_binary,
    chamfer,
    chamfer_against,
    distance_maps,
)
from tests.binary_images import SIZE, every_image, random_images  # noqa: E402
from tests.reference.chamfer_cv import canny_cv, chamfer_cv, distance_cv  # noqa: E402

# OpenCV 5 sums the chamfer steps in float32, so its distances drift from the
# exact ones by up to ~1.5e-6 relative (a few ulps, more along long paths).
CV_RTOL = 3e-6


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return random_images(3000, seed=0)


@pytest.fixture(scope="module")
def cv_edges(images) -> np.ndarray:
    return np.stack([canny_cv(img) > 0 for img in images])


def exact_distance(edges: np.ndarray) -> np.ndarray:
    """Brute force: min over edge pixels of the 3x3 chamfer path length
    a * (max - min) + b * min of |dy|, |dx|, with OpenCV's float32 steps; every
    term is exact in float64 (integers times 24-bit mantissas)."""
    a, b = float(np.float32(0.955)), float(np.float32(1.3693))
    ey, ex = np.nonzero(edges)
    yy, xx = np.mgrid[: edges.shape[0], : edges.shape[1]]
    dy = np.abs(yy.reshape(-1, 1) - ey)
    dx = np.abs(xx.reshape(-1, 1) - ex)
    lo, hi = np.minimum(dy, dx), np.maximum(dy, dx)
    return (a * (hi - lo) + b * lo).min(1).reshape(edges.shape)


# --- Canny -------------------------------------------------------------------------------


def test_direction_rule_matches_opencv_fixed_point_on_every_3x3_neighbourhood():
    """The module classifies directions with 12|dy| < 5|dx| and 5|dy| > 12|dx|;
    OpenCV uses tan(22.5) in 15-bit fixed point. Same answer on binary images."""
    assert CANNY_TG22 == int(0.4142135623730950488016887242097 * (1 << 15) + 0.5)
    kx = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]])
    for code in range(512):
        patch = np.array([(code >> k) & 1 for k in range(9)]).reshape(3, 3)
        dx, dy = int((patch * kx).sum()), int((patch * kx.T).sum())
        ax, ay = abs(dx), abs(dy)
        cv_horiz = (ay << 15) < ax * CANNY_TG22
        cv_vert = not cv_horiz and (ay << 15) > ax * CANNY_TG22 + (ax << 16)
        assert (12 * ay < 5 * ax) == cv_horiz
        assert (5 * ay > 12 * ax) == cv_vert


def test_canny_equals_opencv(images, cv_edges):
    ours = canny_binary(torch.from_numpy(images)).numpy()
    bad = np.nonzero((ours != cv_edges).any(axis=(1, 2)))[0]
    assert bad.size == 0, f"{bad.size} images differ, first {bad[:5]}"


@pytest.mark.parametrize("shape", [(1, 10), (10, 1), (2, 6), (3, 3), (4, 4)])
def test_canny_and_distances_on_every_tiny_image(shape):
    imgs = every_image(*shape)
    edges = canny_binary(torch.from_numpy(imgs)).numpy()
    assert np.array_equal(edges, np.stack([canny_cv(img) > 0 for img in imgs]))
    some = edges[edges.any(axis=(1, 2))][:: max(1, len(edges) // 500)]
    dist = distance_maps(torch.from_numpy(some)).numpy()
    for e, d in zip(some, dist):
        np.testing.assert_allclose(d, distance_cv(e.astype(np.uint8) * 255), rtol=CV_RTOL, atol=1e-6)
        assert np.array_equal(d, exact_distance(e).astype(np.float32))


@pytest.mark.parametrize("shape", [(17, 23), (40, 100), (100, 40)])
def test_canny_and_distances_on_other_sizes(shape):
    imgs = random_images(60, seed=1, h=shape[0], w=shape[1])
    edges = canny_binary(torch.from_numpy(imgs)).numpy()
    assert np.array_equal(edges, np.stack([canny_cv(img) > 0 for img in imgs]))
    dist = distance_maps(torch.from_numpy(edges)).numpy()
    for e, d in zip(edges, dist):
        np.testing.assert_allclose(d, distance_cv(e.astype(np.uint8) * 255), rtol=CV_RTOL, atol=1e-6)
        if 0 < e.sum() <= 600:
            assert np.array_equal(d, exact_distance(e).astype(np.float32))


def test_canny_keeps_leading_dims_and_reads_nonbool_as_nonzero(images):
    x = torch.from_numpy(images[:12])
    ours = canny_binary(x.view(3, 4, SIZE, SIZE).to(torch.uint8) * 7)
    assert ours.shape == (3, 4, SIZE, SIZE) and ours.dtype == torch.bool
    assert torch.equal(ours.view(12, SIZE, SIZE), canny_binary(x))


# --- distance transform ------------------------------------------------------------------


def test_distance_maps_match_opencv(cv_edges):
    ours = distance_maps(torch.from_numpy(cv_edges)).numpy()
    ref = np.stack([distance_cv(e.astype(np.uint8) * 255) for e in cv_edges])
    np.testing.assert_allclose(ours, ref, rtol=CV_RTOL, atol=1e-6)
    empty = ~cv_edges.any(axis=(1, 2))
    assert empty.any() and (ours[empty] == np.finfo(np.float32).max).all()
    assert np.array_equal(ours[empty], ref[empty])


def test_distance_maps_are_the_exact_chamfer_distance(cv_edges):
    counts = cv_edges.sum(axis=(1, 2))
    pick = np.nonzero((counts > 0) & (counts <= 600))[0][::8][:150]
    ours = distance_maps(torch.from_numpy(cv_edges[pick])).numpy()
    for i, d in zip(pick, ours):
        assert np.array_equal(d, exact_distance(cv_edges[i]).astype(np.float32)), i


def test_distance_steps_are_opencv_float32_weights():
    assert STEP_HV == np.float32(0.955) * 2**24 and STEP_DIAG == np.float32(1.3693) * 2**24


# --- Chamfer distance -----------------------------------------------------------------------


def test_fixture_reproduced(fixtures_dir):
    data = np.load(fixtures_dir / "csgnet_chamfer_reference.npz")
    ours = chamfer(torch.from_numpy(data["pred"]), torch.from_numpy(data["target"])).numpy()
    assert ours.dtype == np.float64 and ours.shape == data["chamfer"].shape
    err = np.abs(ours - data["chamfer"])
    assert err.max() <= 1e-4, (err.argmax(), data["kind"][err.argmax()], err.max())


def _pairs(images: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random pairs, and each image against a shifted copy of itself."""
    rng = np.random.default_rng(seed)
    n = len(images)
    a = rng.permutation(n)[:800]
    b = rng.permutation(n)[:800]
    shifted = np.roll(images[a], (1, -2), axis=(1, 2))
    return np.concatenate([images[a], images[a]]), np.concatenate([images[b], shifted])


def test_chamfer_matches_opencv_reference(images):
    pred, target = _pairs(images, seed=2)
    ours = chamfer(torch.from_numpy(pred), torch.from_numpy(target)).numpy()
    ref = np.array([chamfer_cv(p, t) for p, t in zip(pred, target)])
    assert (ref == PENALTY).any() and (ref < PENALTY).sum() > 1000
    err = np.abs(ours - ref)
    # 1e-5 over the range of real shapes; far apart pairs (a lone pixel against
    # another one 60 pixels away) inherit OpenCV's float32 drift, < 1e-6 relative.
    assert err[ref <= 10].max() <= 1e-5
    assert (err <= 1e-5 + 1e-6 * ref).all()


def exact_chamfer(pred: np.ndarray, target: np.ndarray) -> float:
    """CSGNet's CD from OpenCV's edges and the brute-force exact distances."""
    e_p, e_t = canny_cv(pred) > 0, canny_cv(target) > 0
    n_p, n_t = e_p.sum(), e_t.sum()
    if min(n_p, n_t) == 0 or max(n_p, n_t) == e_p.size:
        return PENALTY
    term_p = 255.0 * exact_distance(e_t)[e_p].sum() / (255.0 * n_p + 1)
    term_t = 255.0 * exact_distance(e_p)[e_t].sum() / (255.0 * n_t + 1)
    return (term_p + term_t) / 2


def test_chamfer_is_exact(images):
    pred, target = _pairs(images, seed=6)
    small = (pred.sum(axis=(1, 2)) < 1500) & (target.sum(axis=(1, 2)) < 1500)
    pred, target = pred[small][:60], target[small][:60]
    ours = chamfer(torch.from_numpy(pred), torch.from_numpy(target)).numpy()
    ref = np.array([exact_chamfer(p, t) for p, t in zip(pred, target)])
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=0)


def test_chamfer_against_equals_plain_chamfer(images):
    rng = np.random.default_rng(3)
    n, k = 37, 5
    targets = images[rng.integers(0, len(images), n)]
    cands = images[rng.integers(0, len(images), (n, k))]
    cands[:, 0] = targets  # the target itself among the candidates
    t, c = torch.from_numpy(targets), torch.from_numpy(cands)
    features = TargetFeatures.of(t)
    ours = chamfer_against(c, features)
    plain = chamfer(c, t[:, None].expand_as(c))
    assert ours.shape == (n, k) and ours.dtype == torch.float64
    assert torch.equal(ours, plain)
    assert torch.equal(chamfer_against(c[:, 2], features), plain[:, 2])


def test_self_distance_is_zero_and_penalties(images):
    x = torch.from_numpy(images)
    degenerate = ~canny_binary(x).flatten(1).any(1)
    cd = chamfer(x, x)
    assert (cd[~degenerate] == 0).all() and (cd[degenerate] == PENALTY).all()
    shape = torch.from_numpy(images[2:3])  # a rectangle union
    empty, full = torch.zeros_like(shape), torch.ones_like(shape)
    for p, t in [(empty, shape), (shape, empty), (full, shape), (shape, full), (empty, empty), (full, full)]:
        assert chamfer(p, t).item() == PENALTY
    assert PENALTY == 16.0


def test_chamfer_shapes_and_errors(images):
    x = torch.from_numpy(images[:24])
    y = torch.from_numpy(images[24:48])
    flat = chamfer(x, y)
    assert torch.equal(chamfer(x.view(2, 3, 4, SIZE, SIZE), y.view(2, 3, 4, SIZE, SIZE)), flat.view(2, 3, 4))
    assert chamfer(x[:0], y[:0]).shape == (0,)
    with pytest.raises(ValueError):
        chamfer(x, y[:5])


def test_same_result_with_one_or_more_torch_threads(images):
    pred, target = _pairs(images[:600], seed=4)
    p, t = torch.from_numpy(pred), torch.from_numpy(target)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        single = chamfer(p, t)
        torch.set_num_threads(2)  # chunks on the worker pool
        pooled = chamfer(p, t)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(single, pooled)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(images):
    pred, target = _pairs(images[:400], seed=5)
    p, t = torch.from_numpy(pred), torch.from_numpy(target)
    assert torch.equal(chamfer(p.cuda(), t.cuda()).cpu(), chamfer(p, t))
    assert torch.equal(canny_binary(p.cuda()).cpu(), canny_binary(p))
    features = TargetFeatures.of(t.cuda())
    assert torch.equal(chamfer_against(p.cuda(), features).cpu(), chamfer(p, t))


@pytest.mark.parametrize("n", [1, 7, 80, 300])
def test_numpy_and_torch_sweeps_agree(n, monkeypatch):
    """A sweep of a few images runs on numpy views of the tensor (the same integer steps in place): the same
    distances as the torch sweep, for batches on both sides of the switch."""
    import importlib

    cd = importlib.import_module("plad.metrics.chamfer")   # (plad.metrics.chamfer is also the function's name)
    gen = torch.Generator().manual_seed(n)
    start = torch.randint(0, 40, (64, n, 66), generator=gen, dtype=torch.int32) * cd.STEP_HV
    start[:, :, 0] = start[:, :, -1] = 63 * cd.STEP_HV
    a, b = start.clone(), start.clone()
    cd._sweep_rows(a)
    monkeypatch.setattr(cd, "_NUMPY_SWEEP", 0)
    cd._sweep_rows(b)
    assert torch.equal(a, b) and not torch.equal(a, start)
    part, whole = start.clone(), start.clone()                     # a view of some images, as the pool sweeps
    cd._sweep_rows(part[:, : max(1, n // 2)])
    monkeypatch.setattr(cd, "_NUMPY_SWEEP", 256 * 66)
    cd._sweep_rows(whole[:, : max(1, n // 2)])
    assert torch.equal(part, whole)


@pytest.mark.parametrize("shape, mask_shape", [((64, 5, 64), (64, 5, 64)), ((64, 3, 4, 64), (64, 3, 1, 64)),
                                               ((64, 300, 64), (64, 300, 64))])
def test_numpy_and_torch_masked_sums_agree(shape, mask_shape, monkeypatch):
    """The masked sums of a few images run in numpy (int64 sums, exact): the same float64 totals and counts as
    the torch rows, on strided views as the metric passes them."""
    import importlib

    cd = importlib.import_module("plad.metrics.chamfer")
    gen = torch.Generator().manual_seed(len(shape))
    padded = torch.randint(0, 60, (*shape[:-1], shape[-1] + 2), generator=gen, dtype=torch.int32) * cd.STEP_HV
    values = padded[..., 1:-1]                                        # a strided view, as the sweeps' buffer
    mask = torch.rand(mask_shape, generator=gen) < 0.3
    fast = cd._masked_sums(values, mask, count=True)
    monkeypatch.setattr(cd, "_NUMPY_SUMS", 0)
    slow = cd._masked_sums(values, mask, count=True)
    assert fast[0].dtype == slow[0].dtype == torch.float64 and fast[1].dtype == slow[1].dtype == torch.int64
    assert torch.equal(fast[0], slow[0]) and torch.equal(fast[1], slow[1])
    assert cd._masked_sums(values, mask, count=False)[1] is None
