# size: one algorithm, kept whole: the docstring below (about 100 lines) is the argument that each part
# equals OpenCV bit for bit, and the Canny, distance-transform and CD parts share its flat int8 buffer
# layouts, the CPU chunk sizes and the worker pool; about 550 lines of code, no function over 100.
"""CSGNet's Chamfer distance (CD), batched in torch (numpy for a few images on the CPU), matching OpenCV.

CSGNet scores a predicted canvas P against a target T (bool 64 x 64) as

    E = cv2.Canny(img * 255, 1, 3)                        # {0, 255} edge maps
    D = cv2.distanceTransform(~E, cv2.DIST_L2, 3)         # 3x3 chamfer distance
    CD = ( sum(D_T * E_P) / (sum(E_P) + 1) + sum(D_P * E_T) / (sum(E_T) + 1) ) / 2

with a fixed penalty of 16 when an image or an edge map is empty or full
(docs/domains.md, "Metric: Chamfer distance"). This module computes the same without
OpenCV, on CPU or CUDA tensors, for thousands of pairs per call.

Canny on a {0, 255} image
    Every nonzero Sobel magnitude |dx| + |dy| is a multiple of 255, far above
    both thresholds (1 and 3), so every pixel that survives non-maximum
    suppression (NMS) is a strong edge and hysteresis changes nothing. What
    matters is OpenCV's NMS, exactly: Sobel 3x3 with BORDER_REPLICATE,
    magnitude 0 outside the image, the direction classified with the
    fixed-point tan(22.5 deg), the asymmetric comparisons (``m > previous`` and
    ``m >= next`` horizontally and vertically, ``>`` on both sides diagonally)
    and the diagonal picked by the sign of dx * dy. We run it on the 0/1 image
    in int8 (the factor 255 cancels in every comparison). The result equals
    ``cv2.Canny(img * 255, 1, 3) > 0`` bit for bit (tests/plad/metrics/test_chamfer.py).

Distance transform
    OpenCV 5 runs the 3x3 chamfer transform in float32 with steps
    a = float32(0.955) and b = float32(1.3693) (OpenCV 4 used 16-bit fixed
    point); its float32 accumulation order follows its SIMD code, so its values
    are the true chamfer distances up to a few float32 ulps (relative error up
    to ~1.5e-6, i.e. 1e-4 at distance 90). We compute the true chamfer
    distance exactly instead:
    a = 16022241 and b = 22973042 in units of 2^-24, so every path length is an
    integer and int32 holds the largest 64 x 64 distance (63 b = 1.45e9 units;
    bigger images switch to int64).
    Rather than OpenCV's raster scan we use two separable stages: a shortest
    chamfer path uses one kind of straight step and one kind of diagonal step
    only, so it can be reordered as "the horizontal steps first, then steps
    that all go down (or all up)". Hence
      1. the distance, in pixels, to the nearest edge pixel of the same row,
         for all rows at once (log-step min-scans in int8), then
      2. one downward and one upward sweep over the rows, each row taking the
         min of itself, (row before) + a, and (its two diagonal neighbours) + b.
    The sweeps loop over rows in Python, but each step works on the (N, W)
    rows of the whole batch, so a batch costs 2 x 63 small steps.

Why the odd layouts
    Eager torch on the CPU is bound by memory traffic and by per-row overhead
    on short (64-element) rows, so the hot paths work on flat, contiguous int8
    buffers: Canny on the images padded by one pixel and laid end to end (the
    neighbours of a pixel are then fixed offsets in one flat array), and the
    row scans on rows padded with as many cells as a scan can reach, so that
    no row leaks into the next one. The sweeps keep the batch in (H, N, W)
    order, rows of the whole batch contiguous. Work is chunked so a chunk's
    buffers stay in cache. On CUDA the chunks are simply the whole batch.

Threads
    A batch is thousands of small ops. Torch's intra-op (OpenMP) threads would
    enter a parallel region, with a barrier, for each of them; on a loaded
    machine a barrier waits for a descheduled thread, and we measured a 250x
    slowdown. So on the CPU the chunks run on a small pool of Python threads
    (as many as ``torch.get_num_threads()``), each doing single-threaded ops;
    torch releases the GIL inside ops, so the chunks overlap. The pool is
    created lazily, per process, and the caller's thread settings are untouched.

The CD is evaluated from the exact integer distances, in float64.
"""
from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

PENALTY = 16.0
"""CD of a pair whose image or edge map is empty or full (and of invalid programs)."""

# OpenCV: TG22 = (int)(0.4142135623730950488016887242097 * (1 << 15) + 0.5); a
# pixel is "horizontal" when |dy| << 15 < |dx| * TG22 and "vertical" when
# |dy| << 15 > |dx| * TG22 + (|dx| << 16). On a 0/1 image |dx|, |dy| <= 4, and on
# that range these tests are exactly 12 |dy| < 5 |dx| and 5 |dy| > 12 |dx|
# (tests/plad/metrics/test_chamfer.py checks every 3 x 3 neighbourhood), which fit in int8.
CANNY_TG22 = 13573

UNIT_BITS = 24
"""Distances are integers in units of 2^-24 (exact for float32 steps < 2)."""
STEP_HV = 16022241
"""float32(0.955) * 2^24: OpenCV's horizontal/vertical step for DIST_L2, mask 3."""
STEP_DIAG = 22973042
"""float32(1.3693) * 2^24: OpenCV's diagonal step."""
_UNIT = 2.0**-UNIT_BITS

# CPU chunking: images per Canny / row-scan sub-chunk (buffers of ~0.3 MB stay
# in L2) and at most this many images per task (sweep batch; longer rows
# amortise the per-op overhead).
_SUB_CHUNK = 64
_SWEEP_CHUNK = 1024
# sweeps of at most this many cells a row (images x (W + 2)) run on numpy views on the CPU (_sweep_rows)
_NUMPY_SWEEP = 256 * 66
# masked sums over at most this many images run in numpy on the CPU (_masked_sums)
_NUMPY_SUMS = 256
# CD of images at most 64 pixels wide on the CPU through the compiled kernels of plad.metrics.chamfer_compiled
# (the same numbers, a tenth of the time) where numba is there: None when the process has earned it (plad.jit),
# True from the first call, False never
_COMPILED: bool | None = None
# the tensor path's CPU seconds for a call (its fixed steps) and per pair, for plad.jit's rule
_TENSOR_CALL_SECONDS = 3e-4
_TENSOR_PAIR_SECONDS = 1e-4


# --- execution: chunks on a pool of single-threaded workers -------------------------

_local = threading.local()  # .worker: this thread is a pool worker; .workspace
_pool_lock = threading.Lock()
_pool_state: tuple[int, int, ThreadPoolExecutor] | None = None  # (pid, workers, pool)


def _init_worker() -> None:
    torch.set_num_threads(1)  # per-thread (OpenMP ICV): the caller keeps its own
    _local.worker = True


def _pool(workers: int) -> ThreadPoolExecutor:
    global _pool_state
    with _pool_lock:
        state = _pool_state
        if state is None or state[0] != os.getpid() or state[1] != workers:
            if state is not None and state[0] == os.getpid():
                state[2].shutdown(wait=False)
            pool = ThreadPoolExecutor(workers, thread_name_prefix="plad-chamfer", initializer=_init_worker)
            _pool_state = state = (os.getpid(), workers, pool)
        return state[2]


_OPENMP: bool | None = None


def _openmp() -> bool:
    """torch.set_num_threads is per thread only with the OpenMP backend (the
    usual one); with another backend the pool would change the caller's setting."""
    global _OPENMP
    if _OPENMP is None:
        _OPENMP = "parallel backend: OpenMP" in torch.__config__.parallel_info()
    return _OPENMP


def _run(tasks: list[Callable[[], None]], device: torch.device) -> None:
    """Run independent tasks: inline on CUDA, in a pool worker, with one torch
    thread or without OpenMP; otherwise on the pool (single-threaded ops, see
    Threads in the module docstring)."""
    threads = torch.get_num_threads()
    if device.type != "cpu" or getattr(_local, "worker", False) or threads == 1 or not _openmp():
        for task in tasks:
            task()
        return
    futures = [_pool(threads).submit(task) for task in tasks]
    for future in futures:
        future.result()


def _spans(n: int, images_per_item: int, device: torch.device) -> list[tuple[int, int]]:
    """Split n items (of images_per_item images each) into task ranges: the
    whole batch on CUDA; on the CPU at most _SWEEP_CHUNK images per task and
    at least one task per thread when the batch is big enough."""
    if n == 0:
        return []
    if device.type != "cpu":
        return [(0, n)]
    images = n * max(1, images_per_item)
    per_task = min(_SWEEP_CHUNK, max(_SUB_CHUNK, math.ceil(images / torch.get_num_threads())))
    items = max(1, per_task // max(1, images_per_item))
    return [(i, min(n, i + items)) for i in range(0, n, items)]


# --- Canny ---------------------------------------------------------------------


def _as_batch(images: torch.Tensor) -> tuple[torch.Tensor, tuple[int, ...]]:
    """(..., H, W) any dtype -> bool (N, H, W) and the leading shape."""
    if images.dim() < 2:
        raise ValueError(f"expected (..., H, W) images, got shape {tuple(images.shape)}")
    lead = tuple(images.shape[:-2])
    flat = images.reshape(-1, *images.shape[-2:])
    if flat.dtype != torch.bool:
        flat = flat != 0
    return flat, lead


def _canny_flat(images: torch.Tensor) -> tuple[torch.Tensor, int, int]:
    """Canny edges of bool (n, H, W) images in a flat padded layout.

    Returns (edges, stride, core): edges is bool (n, slot); image i's edge map
    is ``edges[i, :core].view(H + 2, stride)[1:-1, 1:-1]``, with
    stride = W + 2, core = (H + 2) * stride and a False border.
    """
    n, height, width = images.shape
    stride = width + 2
    core = (height + 2) * stride
    slot = (core + 7) // 8 * 8  # multiple of 8 bytes
    margin = stride + 1  # every neighbour offset stays inside the buffer
    length = n * slot
    device = images.device

    # Replicate-padded images, end to end: buf[margin + i * slot + r * stride + c].
    # The margins and slot tails are left uninitialised: they only feed
    # positions outside the images, whose results are never used.
    buf = torch.empty(length + 2 * margin, dtype=torch.int8, device=device)
    xp = buf[margin : margin + length].view(n, slot)[:, :core].view(n, height + 2, stride)
    xp[:, 1:-1, 1:-1] = images
    xp[:, 0, 1:-1] = images[:, 0]
    xp[:, -1, 1:-1] = images[:, -1]
    xp[:, :, 0] = xp[:, :, 1]
    xp[:, :, -1] = xp[:, :, -2]

    # Sobel at every flat position (garbage on the padding, never used):
    # dx = [-1 0 1] across columns, smoothed [1 2 1] along rows; dy likewise.
    hd = buf[margin - stride + 1 : margin + length + stride + 1] - buf[
        margin - stride - 1 : margin + length + stride - 1
    ]  # horizontal differences at positions [-stride, length + stride)
    dx = hd[:length] + hd[2 * stride :]
    dx += hd[stride : stride + length]
    dx += hd[stride : stride + length]
    vd = buf[margin - 1 + stride : margin + length + 1 + stride] - buf[
        margin - 1 - stride : margin + length + 1 - stride
    ]  # vertical differences at positions [-1, length + 1)
    dy = vd[:length] + vd[2:]
    dy += vd[1 : length + 1]
    dy += vd[1 : length + 1]
    ax = dx.abs()
    ay = dy.abs()

    # L1 magnitude, 0 outside the image (OpenCV's magnitude buffer border).
    mbuf = torch.empty(length + 2 * margin, dtype=torch.int8, device=device)
    m = mbuf[margin : margin + length]
    torch.add(ax, ay, out=m)
    mv = m.view(n, slot)
    mv[:, core:] = 0
    mi = mv[:, :core].view(n, height + 2, stride)
    mi[:, 0] = 0
    mi[:, -1] = 0
    mi[:, :, 0] = 0
    mi[:, :, -1] = 0
    m1buf = mbuf - 1  # "m >= next" is "m > next - 1"

    def at(offset: int, base: torch.Tensor = mbuf) -> torch.Tensor:  # neighbour at a flat offset
        return base[margin + offset : margin + offset + length]

    # NMS as one comparison m > q, q chosen by direction:
    #   m > prev and m >= next  <=>  m > max(prev, next - 1)   (horizontal, vertical)
    #   m > prev and m >  next  <=>  m > max(prev, next)       (diagonals)
    q_h = torch.maximum(at(-1), at(1, m1buf))
    q_v = torch.maximum(at(-stride), at(stride, m1buf))
    q_same = torch.maximum(at(-stride - 1), at(stride + 1))  # dx, dy of equal signs
    q_opp = torch.maximum(at(-stride + 1), at(stride - 1))  # opposite signs
    # Direction masks as int8 0 / -1 (arithmetic shift of the sign bit), so the
    # selection is bitwise: q ^ ((q ^ other) & mask) is `other` where mask = -1.
    # horizontal: 12|dy| - 5|dx| < 0; vertical: 12|dx| - 5|dy| = 7m - that < 0.
    t = ay * 12
    t -= ax * 5
    vert = m * 7
    vert -= t
    vert >>= 7
    horiz = t >> 7
    opp = dx * dy
    opp >>= 7
    q = q_same ^ ((q_same ^ q_opp) & opp)
    q ^= (q ^ q_h) & horiz
    q ^= (q ^ q_v) & vert
    edges = m > q  # m = 0 is never an edge: q >= 0
    return edges.view(n, slot), stride, core


def _interior(flat: torch.Tensor, stride: int, core: int, height: int) -> torch.Tensor:
    """(n, slot) flat padded maps -> (n, H, W) view of the image pixels."""
    return flat[:, :core].view(-1, height + 2, stride)[:, 1:-1, 1:-1]


def canny_binary(images: torch.Tensor) -> torch.Tensor:
    """Edge maps of binary images, equal to ``cv2.Canny(img * 255, 1, 3) > 0``.

    images: (..., H, W), bool (any other dtype is read as ``!= 0``).
    Returns bool of the same shape.
    """
    flat, lead = _as_batch(images)
    n, height, width = flat.shape
    out = torch.empty((n, height, width), dtype=torch.bool, device=flat.device)

    def task(start: int, stop: int) -> None:
        sub = _SUB_CHUNK if flat.device.type == "cpu" else stop - start
        for i in range(start, stop, sub):
            edges, stride, core = _canny_flat(flat[i : min(stop, i + sub)])
            out[i : i + edges.shape[0]] = _interior(edges, stride, core, height)

    _run([lambda a=a, b=b: task(a, b) for a, b in _spans(n, 1, flat.device)], flat.device)
    return out.reshape(*lead, height, width)


# --- distance transform ----------------------------------------------------------


@dataclass(frozen=True)
class _Plan:
    """Integer types and constants of the distance transform of H x W images."""

    reach: int  # a row scan's largest total shift, >= W - 1
    px_dtype: torch.dtype  # row scans, distances in pixels
    inf_px: int  # "no edge pixel in this row", in pixels
    unit_dtype: torch.dtype  # sweeps, distances in 2^-24 units

    @property
    def inf_units(self) -> int:
        return self.inf_px * STEP_HV


def _plan(height: int, width: int) -> _Plan:
    reach = (1 << max(0, (width - 1).bit_length())) - 1  # shifts 1, 2, 4, ... < width
    # Any finite chamfer distance is < max(H, W) diagonal steps; "no edge" must
    # exceed it once converted to units.
    inf_px = (max(height, width) - 1) * STEP_DIAG // STEP_HV + 1
    biggest_shift = (reach + 1) // 2
    if inf_px + biggest_shift <= 127:
        px_dtype = torch.int8
    elif inf_px + biggest_shift <= 32767:
        px_dtype = torch.int16
    else:
        px_dtype = torch.int32
    # The sweeps add at most one diagonal step to a value <= inf_px * STEP_HV.
    fits = inf_px * STEP_HV + STEP_DIAG < 2**31
    return _Plan(reach, px_dtype, inf_px, torch.int32 if fits else torch.int64)


def _row_distance_px(edges: torch.Tensor, plan: _Plan) -> torch.Tensor:
    """Pixels to the nearest edge pixel of the same row; inf_px where none.

    edges: bool (n, H, W), any strides. Returns a (n, H, W) view of a flat
    buffer whose rows are padded by ``reach`` cells: a min-plus scan with
    shifts 1, 2, 4, ... (g[x] = min(g[x], g[x -+ k] + k)) reaches at most
    ``reach`` cells, so it never carries a value from one row into the next,
    and the whole buffer can be scanned as one flat array (fast, contiguous).
    """
    n, height, width = edges.shape
    row = width + plan.reach
    g = torch.full((n, height, row), plan.inf_px, dtype=plan.px_dtype, device=edges.device)
    g[:, :, :width].masked_fill_(edges, 0)
    flat = g.view(-1)
    tmp = torch.empty_like(flat)
    for forward in (True, False):
        k = 1
        while k < width:
            t = tmp[: flat.numel() - k]
            if forward:  # from the left
                torch.add(flat[:-k], k, out=t)
                torch.minimum(flat[k:], t, out=flat[k:])
            else:  # from the right
                torch.add(flat[k:], k, out=t)
                torch.minimum(flat[:-k], t, out=flat[:-k])
            k *= 2
    return g[:, :, :width]


def _sweep_rows(r: torch.Tensor) -> None:
    """In place: vertical and diagonal chamfer steps over rows, down then up.

    r: (H, ..., W + 2) integer distances in units, one column of inf_units on
    each side; on entry the row-only distances, on exit the full chamfer
    distance transform.
    """
    height = r.shape[0]
    if r.device.type == "cpu" and r[0].numel() <= _NUMPY_SWEEP:
        # the same integer steps on numpy views of r (in place): on a few images a torch op's overhead is most
        # of its cost, and a search scores a few candidates at a time (1-120 images: 3-5x faster)
        a = r.numpy()
        inner = a[0, ..., 1:-1]
        cand, diag = np.empty(inner.shape, dtype=a.dtype), np.empty(inner.shape, dtype=a.dtype)
        for i in range(1, height):
            _relax_np(a[i - 1], a[i, ..., 1:-1], cand, diag)
        for i in range(height - 2, -1, -1):
            _relax_np(a[i + 1], a[i, ..., 1:-1], cand, diag)
        return
    inner = r[0, ..., 1:-1]
    cand = torch.empty(inner.shape, dtype=r.dtype, device=r.device)
    diag = torch.empty(inner.shape, dtype=r.dtype, device=r.device)
    for i in range(1, height):  # downward: row i from row i - 1
        _relax(r[i - 1], r[i, ..., 1:-1], cand, diag)
    for i in range(height - 2, -1, -1):  # upward: row i from row i + 1
        _relax(r[i + 1], r[i, ..., 1:-1], cand, diag)


def _relax_np(prev: np.ndarray, row: np.ndarray, cand: np.ndarray, diag: np.ndarray) -> None:
    """:func:`_relax` on numpy arrays."""
    np.minimum(prev[..., :-2], prev[..., 2:], out=diag)
    np.add(diag, STEP_DIAG, out=diag)
    np.add(prev[..., 1:-1], STEP_HV, out=cand)
    np.minimum(cand, diag, out=cand)
    np.minimum(row, cand, out=row)


def _relax(prev: torch.Tensor, row: torch.Tensor, cand: torch.Tensor, diag: torch.Tensor) -> None:
    """row = min(row, prev + a, min(prev left, prev right) + b); prev is padded."""
    torch.minimum(prev[..., :-2], prev[..., 2:], out=diag)
    diag += STEP_DIAG
    torch.add(prev[..., 1:-1], STEP_HV, out=cand)
    torch.minimum(cand, diag, out=cand)
    torch.minimum(row, cand, out=row)


def _new_sweep_buffer(height: int, n: int, width: int, plan: _Plan, device: torch.device) -> torch.Tensor:
    """(H, n, W + 2) distances in units with one column of inf_units on each side."""
    r = torch.empty((height, n, width + 2), dtype=plan.unit_dtype, device=device)
    r[:, :, 0] = plan.inf_units
    r[:, :, -1] = plan.inf_units
    return r


def _fill_rows(r: torch.Tensor, start: int, edges: torch.Tensor, plan: _Plan) -> None:
    """Write the row-only distances (units) of edges (n, H, W) into r[:, start:start+n]."""
    px = _row_distance_px(edges, plan)
    dst = r[:, start : start + edges.shape[0], 1:-1]
    dst.copy_(px.permute(1, 0, 2))
    dst *= STEP_HV


def _edges_into(
    images: torch.Tensor, r: torch.Tensor, r_start: int, e: torch.Tensor, e_start: int, plan: _Plan
) -> None:
    """Canny of images (n, H, W): row-only distances into r[:, r_start:] and
    the edges into e[:, e_start:], both in (H, N, .) order."""
    n, height, _ = images.shape
    sub = _SUB_CHUNK if images.device.type == "cpu" else max(1, n)
    for i in range(0, n, sub):
        flat, stride, core = _canny_flat(images[i : i + sub])
        edges = _interior(flat, stride, core, height)
        _fill_rows(r, r_start + i, edges, plan)
        e[:, e_start + i : e_start + i + edges.shape[0]] = edges.permute(1, 0, 2)


def _rows_from_edges(edges: torch.Tensor, r: torch.Tensor, plan: _Plan) -> None:
    """Row-only distances of given edge maps (n, H, W) into r (H, n, W + 2)."""
    n = edges.shape[0]
    sub = _SUB_CHUNK if edges.device.type == "cpu" else max(1, n)
    for i in range(0, n, sub):
        _fill_rows(r, i, edges[i : i + sub], plan)


class _Workspace:
    """Sweep and edge buffers of one thread, reused across chunks and calls on
    the CPU: fresh multi-MB buffers cost page faults on every chunk (measured:
    as much as the sweeps themselves). A thread keeps one (about 21 MB for
    1024 images of 64 x 64) for the life of the thread."""

    def __init__(self, height: int, width: int, capacity: int, plan: _Plan, device: torch.device):
        self.key = (height, width, capacity, plan.unit_dtype, str(device))
        self.r = _new_sweep_buffer(height, capacity, width, plan, device)
        self.e = torch.empty((height, capacity, width), dtype=torch.bool, device=device)

    def take(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(r, e) views for n images; r's border columns stay inf_units."""
        return self.r[:, :n], self.e[:, :n]


def _workspace(height: int, width: int, n: int, plan: _Plan, device: torch.device) -> _Workspace:
    if device.type != "cpu":
        return _Workspace(height, width, n, plan, device)
    capacity = max(n, _SWEEP_CHUNK)
    work = getattr(_local, "workspace", None)
    if work is None or work.key != (height, width, capacity, plan.unit_dtype, str(device)):
        work = _local.workspace = _Workspace(height, width, capacity, plan, device)
    return work


def distance_maps(edges: torch.Tensor) -> torch.Tensor:
    """Chamfer distance to the nearest edge pixel, as OpenCV computes it.

    edges: bool (..., H, W). Returns float32 (..., H, W) equal to
    ``cv2.distanceTransform((~edges).astype(uint8) * 255, cv2.DIST_L2, 3)``
    up to OpenCV's own float32 rounding: we return the exact chamfer distance
    rounded once to float32, OpenCV 5 accumulates it in float32 (a few ulps
    apart). Maps without any edge pixel are float32 max, like OpenCV's.
    """
    flat, lead = _as_batch(edges)
    n, height, width = flat.shape
    plan = _plan(height, width)
    out = torch.empty((n, height, width), dtype=torch.float32, device=flat.device)

    def task(start: int, stop: int) -> None:
        r, _ = _workspace(height, width, stop - start, plan, flat.device).take(stop - start)
        _rows_from_edges(flat[start:stop], r, plan)
        _sweep_rows(r)
        units = r[:, :, 1:-1].permute(1, 0, 2)
        out[start:stop] = units.to(torch.float64) * _UNIT

    _run([lambda a=a, b=b: task(a, b) for a, b in _spans(n, 1, flat.device)], flat.device)
    out[~flat.flatten(1).any(1)] = torch.finfo(torch.float32).max
    return out.reshape(*lead, height, width)


# --- Chamfer distance ---------------------------------------------------------------


def _directed(total_units: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """sum(D * E) / (sum(E) + 1) with E in {0, 255}, from sum(D over E) in units."""
    return (total_units * (255.0 * _UNIT)) / (counts.to(torch.float64) * 255.0 + 1.0)


def _degenerate(counts: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Edge map empty or full. An empty or full image has no edges at all (its
    Sobel is 0 with replicated borders), so this also covers the image test."""
    return (counts == 0) | (counts == height * width)


def _masked_sums(
    values: torch.Tensor, mask: torch.Tensor, count: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """sum(values * mask) over H and W, and optionally sum(mask), per image.

    values: integer distances in units, mask: bool; both (H, ..., W),
    broadcastable. Row by row (the buffers stay small and in cache): the
    products are exact in the values' integer type, their sums over W exact in
    float64 (integers < 2^53). Returns float64 (...) and int64 (...) or None.
    """
    shape = torch.broadcast_shapes(values.shape, mask.shape)[1:]
    device = values.device
    if device.type == "cpu" and math.prod(shape[:-1]) <= _NUMPY_SUMS:
        # a few images: two numpy operations instead of four torch ones per row. The sum is exact either way
        # (integers below 2^53), so summed in int64 and converted it is the same float64
        picked = np.where(mask.numpy(), values.numpy(), 0)
        total = torch.from_numpy(picked.sum(axis=(0, picked.ndim - 1), dtype=np.int64).astype(np.float64))
        if not count:
            return total, None
        return total, torch.from_numpy(np.broadcast_to(mask.numpy(), picked.shape).sum(
            axis=(0, picked.ndim - 1), dtype=np.int64))
    product = torch.empty(shape, dtype=values.dtype, device=device)
    wide = torch.empty(shape, dtype=torch.float64, device=device)
    total = torch.zeros(shape[:-1], dtype=torch.float64, device=device)
    counts = torch.zeros(shape, dtype=torch.int32, device=device) if count else None
    for i in range(values.shape[0]):
        torch.mul(values[i], mask[i], out=product)
        wide.copy_(product)
        total += wide.sum(-1)
        if counts is not None:
            counts += mask[i]
    return total, None if counts is None else counts.sum(-1, dtype=torch.int64)


def _check_pair_shapes(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape or pred.dim() < 2:
        raise ValueError(
            f"pred and target must be (..., H, W) of equal shape, got {tuple(pred.shape)} "
            f"and {tuple(target.shape)}"
        )


def _compiled(device: torch.device, width: int, pairs: int):
    """plad.metrics.chamfer_compiled where it applies (CPU, width <= 64, numba importable, plad.jit's rule for
    a call of ``pairs`` pairs), else None."""
    from plad import jit

    if device.type != "cpu" or width > 64:
        return None
    return jit.kernels("plad.metrics.chamfer_compiled", _COMPILED, _TENSOR_CALL_SECONDS + pairs * _TENSOR_PAIR_SECONDS)


def _cd_from_sums(over_p: np.ndarray, counts_p: np.ndarray, over_t: np.ndarray, counts_t: torch.Tensor,
                  bad_t: torch.Tensor | None, height: int, width: int) -> torch.Tensor:
    """CD from the compiled kernels' exact int64 sums: the same float64 operations as the tensor path."""
    counts_p_t = torch.from_numpy(counts_p)
    cd = (_directed(torch.from_numpy(over_p.astype(np.float64)), counts_p_t)
          + _directed(torch.from_numpy(over_t.astype(np.float64)), counts_t)) / 2
    bad = _degenerate(counts_p_t, height, width) | (_degenerate(counts_t, height, width) if bad_t is None else bad_t)
    return cd.masked_fill(bad, PENALTY)


def chamfer(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CSGNet's CD of each pair: bool (..., H, W) x 2 -> float64 (...).

    Degenerate pairs (an image or an edge map empty or full) score PENALTY.
    Lower is better; 0 for a (non-degenerate) image against itself.
    """
    _check_pair_shapes(pred, target)
    p, lead = _as_batch(pred)
    t, _ = _as_batch(target.to(pred.device))
    n, height, width = p.shape
    device = p.device
    compiled = _compiled(device, width, n)
    if compiled is not None:
        rows_p, rows_t = compiled.pack_rows(p.numpy()), compiled.pack_rows(t.numpy())
        sums = np.zeros((n, 4), dtype=np.int64)  # sum of D_T over E_P, |E_P|, sum of D_P over E_T, |E_T|
        _run([lambda a=a, b=b: compiled.pair_sums(rows_p[a:b], rows_t[a:b], width, STEP_HV, STEP_DIAG,
                                                           sums[a:b])
              for a, b in _spans(n, 2, device)], device)
        out = _cd_from_sums(sums[:, 0], sums[:, 1], sums[:, 2], torch.from_numpy(sums[:, 3]), None, height, width)
        return out.reshape(lead)
    plan = _plan(height, width)
    out = torch.empty(n, dtype=torch.float64, device=device)

    def task(start: int, stop: int) -> None:
        m = stop - start
        # 2m images, predictions first, in r (H, 2m, W + 2). The edges go in
        # swapped (targets first), so that image j's distances meet its
        # partner's edges: the sum over E_T of D_P and the sum over E_P of D_T
        # come out of one pass over (H, 2m, W).
        r, swapped = _workspace(height, width, 2 * m, plan, device).take(2 * m)
        _edges_into(p[start:stop], r, 0, swapped, m, plan)
        _edges_into(t[start:stop], r, m, swapped, 0, plan)
        _sweep_rows(r)
        # [:m] sum of D_P over E_T and |E_T|, [m:] sum of D_T over E_P and |E_P|
        totals, counts = _masked_sums(r[:, :, 1:-1], swapped, count=True)
        counts_t, counts_p = counts[:m], counts[m:]
        cd = (_directed(totals[m:], counts_p) + _directed(totals[:m], counts_t)) / 2
        bad = _degenerate(counts_p, height, width) | _degenerate(counts_t, height, width)
        out[start:stop] = cd.masked_fill(bad, PENALTY)

    _run([lambda a=a, b=b: task(a, b) for a, b in _spans(n, 2, device)], device)
    return out.reshape(lead)


@dataclass(frozen=True)
class TargetFeatures:
    """Edges and distance maps of N targets, computed once, for many candidates.

    Build with ``TargetFeatures.of(targets)`` (bool (N, H, W)); pass to
    ``chamfer_against``. Fields, in (H, N, W) order (rows of the batch
    contiguous, as the sweeps use them):
      edges: bool (H, N, W) Canny edge maps
      dist: int (H, N, W) chamfer distance transforms in 2^-24 units
      counts: int64 (N,) edge pixel counts
      degenerate: bool (N,) target image or edge map empty or full
    """

    edges: torch.Tensor
    dist: torch.Tensor
    counts: torch.Tensor
    degenerate: torch.Tensor

    @staticmethod
    def of(targets: torch.Tensor) -> TargetFeatures:
        if targets.dim() != 3:
            raise ValueError(f"targets must be (N, H, W), got {tuple(targets.shape)}")
        t, _ = _as_batch(targets)
        n, height, width = t.shape
        plan = _plan(height, width)
        device = t.device
        r = _new_sweep_buffer(height, n, width, plan, device)
        e = torch.empty((height, n, width), dtype=torch.bool, device=device)
        counts = torch.zeros(n, dtype=torch.int64, device=device)

        def task(start: int, stop: int) -> None:
            _edges_into(t[start:stop], r, start, e, start, plan)
            _sweep_rows(r[:, start:stop])
            count = torch.zeros((stop - start, width), dtype=torch.int32, device=device)
            for i in range(height):
                count += e[i, start:stop]
            counts[start:stop] = count.sum(-1, dtype=torch.int64)

        _run([lambda a=a, b=b: task(a, b) for a, b in _spans(n, 1, device)], device)
        return TargetFeatures(e, r[:, :, 1:-1], counts, _degenerate(counts, height, width))

    def __len__(self) -> int:
        return self.edges.shape[1]

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the targets."""
        return self.edges.shape[0], self.edges.shape[2]

    def to(self, device: torch.device | str) -> TargetFeatures:
        return TargetFeatures(*(x.to(device) for x in (self.edges, self.dist, self.counts, self.degenerate)))


def chamfer_against(pred: torch.Tensor, features: TargetFeatures) -> torch.Tensor:
    """CD of candidates against precomputed targets.

    pred: bool (N, K, H, W) -- K candidates for each of the N targets -- or
    (N, H, W), one candidate each. Returns float64 (N, K) or (N,), equal to
    ``chamfer(pred, targets[:, None].expand_as(pred))``; only the candidates
    go through Canny and the distance transform.
    """
    single = pred.dim() == 3
    if single:
        pred = pred[:, None]
    height, width = features.shape
    if pred.dim() != 4 or pred.shape[0] != len(features) or tuple(pred.shape[2:]) != (height, width):
        raise ValueError(
            f"pred must be (N, K, {height}, {width}) or (N, {height}, {width}) with N = "
            f"{len(features)}, got {tuple(pred.shape)}"
        )
    n, k = pred.shape[:2]
    device = pred.device
    compiled = _compiled(device, width, n * k) if features.edges.device == device else None
    if compiled is not None:
        rows_t = getattr(features, "_rows", None)
        if rows_t is None:  # the targets' edge rows, packed once per TargetFeatures
            rows_t = compiled.pack_rows(features.edges.permute(1, 0, 2).numpy())
            object.__setattr__(features, "_rows", rows_t)
        flat, _ = _as_batch(pred.reshape(n * k, height, width))
        rows_p = compiled.pack_rows(flat.numpy()).reshape(n, k, height)
        dist = features.dist.numpy()
        sums = np.zeros((n, k, 3), dtype=np.int64)  # sum of D_T over E_P, |E_P|, sum of D_P over E_T
        _run([lambda a=a, b=b: compiled.against_sums(rows_p[a:b], width, rows_t[a:b], dist[:, a:b],
                                                              STEP_HV, STEP_DIAG, sums[a:b])
              for a, b in _spans(n, k, device)], device)
        out = _cd_from_sums(sums[..., 0], sums[..., 1], sums[..., 2], features.counts[:, None].expand(n, k),
                            features.degenerate[:, None], height, width)
        return out[:, 0] if single else out
    plan = _plan(height, width)
    out = torch.empty((n, k), dtype=torch.float64, device=device)

    def task(start: int, stop: int) -> None:
        m = stop - start
        flat, _ = _as_batch(pred[start:stop].reshape(m * k, height, width))
        r, e_p = _workspace(height, width, m * k, plan, device).take(m * k)
        _edges_into(flat, r, 0, e_p, 0, plan)
        # Candidates as (H, m, K, .) against their targets as (H, m, 1, .).
        e_t = features.edges[:, start:stop, None]
        d_t = features.dist[:, start:stop, None]
        e_p4 = e_p.view(height, m, k, width)
        _sweep_rows(r)
        d_p4 = r.view(height, m, k, width + 2)[..., 1:-1]
        over_t, _ = _masked_sums(d_p4, e_t, count=False)  # D_P over E_T
        over_p, counts_p = _masked_sums(d_t, e_p4, count=True)  # D_T over E_P, |E_P|
        counts_t = features.counts[start:stop, None].expand(m, k)
        cd = (_directed(over_p, counts_p) + _directed(over_t, counts_t)) / 2
        bad = _degenerate(counts_p, height, width) | features.degenerate[start:stop, None]
        out[start:stop] = cd.masked_fill(bad, PENALTY)

    _run([lambda a=a, b=b: task(a, b) for a, b in _spans(n, k, device)], device)
    return out[:, 0] if single else out
