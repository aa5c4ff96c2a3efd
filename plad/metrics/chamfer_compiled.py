"""CSGNet's Chamfer distance on the CPU, compiled with numba, for images at most 64 pixels wide.

The same numbers as the tensor path of :mod:`plad.metrics.chamfer` bit for bit (its docstring argues each part
against OpenCV): the same Canny, the same exact chamfer distances in integer units of 2^-24, summed exactly in
int64. What differs is how little is computed. A 64-pixel row of an image or an edge map is one uint64 (bit x =
pixel x), and

* Canny: a pixel whose 3 x 3 neighbourhood (borders replicated) is uniform has Sobel 0, so magnitude 0, and is
  never an edge; the others (the few around the boundary) are found with a handful of bit operations per row,
  and only they get the Sobel gradients and the non-maximum suppression, exactly as OpenCV's rule.
* Distances: CD needs the distance transform only at the other image's edge pixels, not at all 4,096 pixels.
  The chamfer distance between pixels dy rows and dx columns apart is ``(M - m) a + m b`` with
  ``M = max(|dx|, |dy|)``, ``m = min(|dx|, |dy|)`` (a shortest path of straight steps a and diagonal steps b,
  b < 2a): increasing in |dx| for a fixed row, so a row's nearest edge pixel (two bit scans of its uint64) is the
  only candidate of that row, and no row ``v`` away can give less than ``v a``: rows are visited outward from the
  pixel's own until that bound passes the best distance found. The minimum over all edge pixels is the exact
  chamfer distance the sweeps compute.

The kernels release the GIL (the module's thread pool runs chunks side by side). numba is optional: without it
:func:`available` is False and :mod:`plad.metrics.chamfer` keeps its tensor path; when a process switches to
these kernels is :mod:`plad.jit`'s rule. Compiled code is cached beside this file (``cache=True``), so numba
compiles once per install, later processes load it.
"""
from __future__ import annotations

import numpy as np

from plad.jit import compiler

njit = compiler()   # None without numba: the caller keeps its tensor path

MAX_WIDTH = 64
"""Widest image a row's uint64 holds."""

if njit is not None:
    from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

__all__ = ["MAX_WIDTH", "available", "pack_rows"]


def available() -> bool:
    """Whether the kernels can run here (numba importable)."""
    return njit is not None


def pack_rows(images: np.ndarray) -> np.ndarray:
    """bool (n, H, W) with W <= 64 -> uint64 (n, H), bit x of a row = pixel x."""
    n, height, width = images.shape
    if width > MAX_WIDTH:
        raise ValueError(f"rows of at most {MAX_WIDTH} pixels, got width {width}")
    if width != MAX_WIDTH:
        wide = np.zeros((n, height, MAX_WIDTH), dtype=bool)
        wide[:, :, :width] = images
        images = wide
    # 8 pixels (bytes 0/1) per uint64 word, gathered into one byte by a multiplication
    words = np.ascontiguousarray(images, dtype=bool).view(np.uint64).reshape(n, height, MAX_WIDTH // 8)
    out = np.empty((n, height), dtype=np.uint64)
    _pack(words, out)
    return out


if njit is not None:
    _ONE = np.uint64(1)
    _FAR = np.int64(1) << np.int64(62)

    @njit(cache=True, nogil=True)
    def _pack(words, out):
        """words: uint64 (n, H, 8), each byte one pixel (0 or 1, little-endian); out: uint64 (n, H)."""
        n, height, k = words.shape
        for i in range(n):
            for y in range(height):
                row = np.uint64(0)
                for j in range(k):
                    # byte b of the word lands on bit 56 + b of the product: its top byte holds the 8 pixels
                    row |= ((words[i, y, j] * np.uint64(0x0102040810204080)) >> np.uint64(56)) << np.uint64(8 * j)
                out[i, y] = row

    @njit(cache=True, nogil=True)
    def _popcount(x):
        x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
        x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
        x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
        return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))

    def _sobel_table() -> np.ndarray:
        """int8 (512, 2): the L1 magnitude and the direction class of every 3 x 3 neighbourhood, indexed by its
        code (bits 0-2 the row above, 3-5 the pixel's row, 6-8 the row below; in each, x - 1, x, x + 1).
        Classes: 0 vertical (m > up, m >= down), 1 horizontal (m > left, m >= right), 2 the diagonal of opposite
        signs, 3 the other (both strict): OpenCV's fixed-point tan 22.5 deg, as plad.metrics.chamfer states it."""
        table = np.zeros((512, 2), dtype=np.int8)
        for code in range(512):
            a, c, b = [[(code >> (3 * r + i)) & 1 for i in range(3)] for r in range(3)]
            dx = (a[2] + 2 * c[2] + b[2]) - (a[0] + 2 * c[0] + b[0])
            dy = (b[0] + 2 * b[1] + b[2]) - (a[0] + 2 * a[1] + a[2])
            ax, ay = abs(dx), abs(dy)
            if 12 * ax - 5 * ay < 0:
                cls = 0
            elif 12 * ay - 5 * ax < 0:
                cls = 1
            elif dx * dy < 0:
                cls = 2
            else:
                cls = 3
            table[code] = (ax + ay, cls)
        return table

    _SOBEL = _sobel_table()

    @njit(cache=True, nogil=True)
    def _triple(row, x, width):
        """Pixels x - 1, x, x + 1 of a row as 3 bits, the borders replicated."""
        if 0 < x < width - 1:
            return np.int64((row >> np.uint64(x - 1)) & np.uint64(7))
        left = np.int64((row >> np.uint64(max(x - 1, 0))) & _ONE)
        mid = np.int64((row >> np.uint64(x)) & _ONE)
        right = np.int64((row >> np.uint64(min(x + 1, width - 1))) & _ONE)
        return left | (mid << 1) | (right << 2)

    @njit(cache=True, nogil=True)
    def _canny(rows, height, width, mag, cls, cand, out):
        """Canny edges of one binary image (rows uint64 (H,)) into out (uint64 (H,)).

        mag: int8 (H + 2, W + 2) scratch, all zero on entry and on exit (the magnitude with OpenCV's border of 0);
        cls: int8 (H, W) and cand: uint64 (H,) scratch. The rule is :func:`plad.metrics.chamfer._canny_flat`'s."""
        full = ~np.uint64(0) if width == 64 else (_ONE << np.uint64(width)) - _ONE
        top = _ONE << np.uint64(width - 1)
        for y in range(height):
            a = rows[max(y - 1, 0)]
            c = rows[y]
            b = rows[min(y + 1, height - 1)]
            any_v = a | c | b
            all_v = a & c & b
            # left neighbour's bit at x (x = 0 replicated) and the right one's (x = W - 1 replicated)
            any3 = any_v | ((any_v << _ONE) | (any_v & _ONE)) | ((any_v >> _ONE) | (any_v & top))
            all3 = all_v & ((all_v << _ONE) | (all_v & _ONE)) & ((all_v >> _ONE) | (all_v & top))
            cand[y] = any3 & ~all3 & full
        # the magnitude and direction class of each candidate, from its 3 x 3 neighbourhood's code
        for y in range(height):
            bits = cand[y]
            if not bits:
                continue
            a = rows[max(y - 1, 0)]
            c = rows[y]
            b = rows[min(y + 1, height - 1)]
            while bits:
                x = np.int64(trailing_zeros(bits))
                bits &= bits - _ONE
                code = _triple(a, x, width) | (_triple(c, x, width) << 3) | (_triple(b, x, width) << 6)
                mag[y + 1, x + 1] = _SOBEL[code, 0]
                cls[y, x] = _SOBEL[code, 1]
        # non-maximum suppression along the direction class
        for y in range(height):
            out[y] = np.uint64(0)
            bits = cand[y]
            py = y + 1
            while bits:
                x = np.int64(trailing_zeros(bits))
                bits &= bits - _ONE
                px = x + 1
                m = mag[py, px]
                if m == 0:
                    continue
                k = cls[y, x]
                if k == 0:
                    q = max(mag[py - 1, px], mag[py + 1, px] - 1)
                elif k == 1:
                    q = max(mag[py, px - 1], mag[py, px + 1] - 1)
                elif k == 2:
                    q = max(mag[py - 1, px + 1], mag[py + 1, px - 1])
                else:
                    q = max(mag[py - 1, px - 1], mag[py + 1, px + 1])
                if m > q:
                    out[y] |= _ONE << np.uint64(x)
        for y in range(height):  # the scratch back to zero
            bits = cand[y]
            while bits:
                x = np.int64(trailing_zeros(bits))
                bits &= bits - _ONE
                mag[y + 1, x + 1] = 0

    @njit(cache=True, nogil=True)
    def _nearest_in_row(row, x):
        """Columns from x to the nearest set bit of a nonzero row."""
        best = np.int64(64)
        right = row >> np.uint64(x)
        if right:
            best = np.int64(trailing_zeros(right))
        left = row << np.uint64(63 - x)
        if left:
            d = np.int64(leading_zeros(left))
            if d < best:
                best = d
        return best

    @njit(cache=True, nogil=True)
    def _distance(edges, height, y, x, a, b):
        """Exact chamfer distance (units) from (y, x) to the nearest set bit of edges (uint64 (H,), not all zero),
        with straight steps a and diagonal steps b (units)."""
        best = _FAR
        v = 0
        while v < height and v * a < best:
            for yy in (y - v, y + v):
                if 0 <= yy < height and edges[yy]:
                    u = _nearest_in_row(edges[yy], x)
                    if u >= v:
                        d = (u - v) * a + v * b
                    else:
                        d = (v - u) * a + u * b
                    if d < best:
                        best = d
                if v == 0:
                    break
            v += 1
        return best

    @njit(cache=True, nogil=True)
    def _sum_over(edges, other, height, a, b):
        """Sum over the set bits of edges of the distance to other's set bits (0 where other has none)."""
        for y in range(height):
            if other[y]:
                break
        else:
            return np.int64(0)
        total = np.int64(0)
        for y in range(height):
            bits = edges[y]
            while bits:
                x = np.int64(trailing_zeros(bits))
                bits &= bits - _ONE
                total += _distance(other, height, y, x, a, b)
        return total

    @njit(cache=True, nogil=True)
    def _count(edges, height):
        total = np.int64(0)
        for y in range(height):
            total += _popcount(edges[y])
        return total

    @njit(cache=True, nogil=True)
    def _canny_scratch(height, width):
        """_canny's scratch for images of height x width: mag (zeroed), cls and cand."""
        return (np.zeros((height + 2, width + 2), dtype=np.int8), np.empty((height, width), dtype=np.int8),
                np.empty(height, dtype=np.uint64))

    @njit(cache=True, nogil=True)
    def pair_sums(pred, target, width, a, b, out):
        """For each pair of images (uint64 rows (n, H) each): out[i] = (sum of D_T over E_P, |E_P|,
        sum of D_P over E_T, |E_T|), int64, distances in units of steps a (straight) and b (diagonal)."""
        n, height = pred.shape
        mag, cls, cand = _canny_scratch(height, width)
        e_p = np.empty(height, dtype=np.uint64)
        e_t = np.empty(height, dtype=np.uint64)
        for i in range(n):
            _canny(pred[i], height, width, mag, cls, cand, e_p)
            _canny(target[i], height, width, mag, cls, cand, e_t)
            out[i, 0] = _sum_over(e_p, e_t, height, a, b)
            out[i, 1] = _count(e_p, height)
            out[i, 2] = _sum_over(e_t, e_p, height, a, b)
            out[i, 3] = _count(e_t, height)

    @njit(cache=True, nogil=True)
    def edges_of(images, width, out):
        """Canny edges of images (uint64 rows (n, H)) into out (n, H)."""
        n, height = images.shape
        mag, cls, cand = _canny_scratch(height, width)
        for i in range(n):
            _canny(images[i], height, width, mag, cls, cand, out[i])

    @njit(cache=True, nogil=True)
    def against_sums(pred, width, target_edges, target_dist, a, b, out):
        """K candidates of each of N targets: pred uint64 (N, K, H); target_edges uint64 (N, H); target_dist int
        (H, N, W), the targets' distance transforms in units. out[i, k] = (sum of D_T over E_P, |E_P|, sum of
        D_P over E_T), int64."""
        n, k, height = pred.shape
        mag, cls, cand = _canny_scratch(height, width)
        e_p = np.empty(height, dtype=np.uint64)
        for i in range(n):
            for j in range(k):
                _canny(pred[i, j], height, width, mag, cls, cand, e_p)
                over_p = np.int64(0)
                for y in range(height):
                    bits = e_p[y]
                    while bits:
                        x = np.int64(trailing_zeros(bits))
                        bits &= bits - _ONE
                        over_p += np.int64(target_dist[y, i, x])
                out[i, j, 0] = over_p
                out[i, j, 1] = _count(e_p, height)
                out[i, j, 2] = _sum_over(target_edges[i], e_p, height, a, b)
