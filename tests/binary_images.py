"""Binary images of many kinds, seeded, for the tests of the Chamfer metric (its tensor and compiled paths)."""
from __future__ import annotations

import numpy as np

SIZE = 64


def _rects(rng, h, w):
    img = np.zeros((h, w), bool)
    for _ in range(rng.integers(1, 6)):
        y, x = rng.integers(-8, h), rng.integers(-8, w)
        img[max(y, 0) : y + rng.integers(1, 40), max(x, 0) : x + rng.integers(1, 40)] = True
    return img


def _discs(rng, h, w):
    yy, xx = np.mgrid[:h, :w]
    img = np.zeros((h, w), bool)
    for _ in range(rng.integers(1, 5)):
        cy, cx, r = rng.uniform(-10, h + 10), rng.uniform(-10, w + 10), rng.uniform(0.5, 30)
        img ^= (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
    return img


def _blobs(rng, h, w):
    field = rng.random((h // 8 + 2, w // 8 + 2))
    field = np.kron(field, np.ones((8, 8)))[:h, :w]
    for _ in range(3):  # box blur
        field = (field + np.roll(field, 1, 0) + np.roll(field, 1, 1) + np.roll(field, -1, 0)) / 4
    return field > rng.uniform(0.3, 0.7)


def _noise(rng, h, w):
    return rng.random((h, w)) < rng.choice([0.005, 0.02, 0.1, 0.5, 0.9])


def _pixels(rng, h, w):
    img = np.zeros((h, w), bool)
    corners = [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1)]
    for _ in range(rng.integers(1, 4)):
        y, x = corners[rng.integers(4)] if rng.random() < 0.3 else (rng.integers(h), rng.integers(w))
        img[y, x] = True
    return img


def _lines(rng, h, w):
    img = np.zeros((h, w), bool)
    for _ in range(rng.integers(1, 4)):
        kind, k = rng.integers(3), rng.integers(0, min(h, w))
        if kind == 0:
            img[k, rng.integers(0, w // 2) : rng.integers(w // 2, w + 1)] = True
        elif kind == 1:
            img[rng.integers(0, h // 2) : rng.integers(h // 2, h + 1), k] = True
        else:
            idx = np.arange(min(h, w) - k)
            img[idx, idx + k if rng.random() < 0.5 else (w - 1 - idx - k)] = True
    return img


def _checker(rng, h, w):
    cell = int(rng.integers(1, 4))
    yy, xx = np.mgrid[:h, :w]
    return ((yy // cell + xx // cell) % 2).astype(bool)


KINDS = [_rects, _discs, _blobs, _noise, _pixels, _lines, _checker]


def random_images(n: int, seed: int, h: int = SIZE, w: int = SIZE) -> np.ndarray:
    """n bool images: every kind, plain and complemented, plus empty and full."""
    rng = np.random.default_rng(seed)
    out = [np.zeros((h, w), bool), np.ones((h, w), bool)]
    while len(out) < n:
        img = KINDS[len(out) % len(KINDS)](rng, h, w)
        out.append(~img if rng.random() < 0.25 else img)
    return np.stack(out)


def every_image(h: int, w: int) -> np.ndarray:
    """All 2^(h*w) bool images of size h x w."""
    codes = np.arange(2 ** (h * w))[:, None] >> np.arange(h * w)
    return (codes & 1).astype(bool).reshape(-1, h, w)
