"""CSGNet's Chamfer distance (CD), batched in pure torch and exact to OpenCV.

CSGNet scores a predicted canvas P against a target T (bool 64 x 64) as

    E = cv2.Canny(img * 255, 1, 3)                        # {0, 255} edge maps
    D = cv2.distanceTransform(~E, cv2.DIST_L2, 3)         # 3x3 chamfer distance
    CD = ( sum(D_T * E_P) / (sum(E_P) + 1) + sum(D_P * E_T) / (sum(E_T) + 1) ) / 2

with a fixed penalty of 16 when an image or an edge map is empty or full
(../shared/specs/csg2d.md, "Metric"). This module reproduces that without
OpenCV, on CPU or CUDA tensors, for thousands of pairs per call.

Canny on a {0, 255} image
    Every nonzero Sobel magnitude |dx| + |dy| is a multiple of 255, far above
    both thresholds (1 and 3), so every pixel that survives non-maximum
    suppression (NMS) is a strong edge and hysteresis changes nothing. What
    matters is OpenCV's exact NMS: Sobel 3x3 with BORDER_REPLICATE, magnitude 0
    outside the image, the direction classified with the fixed-point tan(22.5)
    (TG22 = 13573 / 2^15), the asymmetric comparisons (``m > previous`` and
    ``m >= next`` horizontally and vertically, ``>`` on both sides on the
    diagonals) and the diagonal chosen by the sign of dx * dy. We run it on the
    0/1 image (the factor 255 cancels in every comparison) in int8.

Distance transform
    OpenCV 5 runs the 3x3 chamfer transform in float32 with weights
    a = float32(0.955) and b = float32(1.3693) (OpenCV 4 used 16-bit fixed
    point); its float32 accumulation order depends on its SIMD code, so its
    values are the true chamfer distances up to a few float32 ulps (<= 4e-5 at
    distance 90). We compute the true chamfer distance exactly: a = 16022241
    and b = 22973042 in units of 2^-24, so every path length is an integer and
    int32 holds the largest 64 x 64 distance (63 b = 1.45e9 units). The
    transform is done in two separable stages instead of OpenCV's raster pass:
    a shortest chamfer path only uses one kind of straight step and one kind of
    diagonal step, so it can be reordered as "all horizontal steps first, then
    steps that all go down (or all up)". Hence
        1. the horizontal distance to the nearest edge pixel of the same row,
           for all rows at once (log-step min-scans in int8), then
        2. one downward and one upward sweep over the rows, each row taking the
           min of itself and (row above/below) + a, (its diagonal neighbours) + b.
    Step 2 is a Python loop over rows, but each step works on (N, W) slices of
    the whole batch, so a batch of thousands of images costs 2 x 63 small ops.

The CD is then evaluated from integer sums (exact), in float64.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

PENALTY = 16.0
"""CD of a pair whose image or edge map is empty or full (and of invalid programs)."""

# --- Canny ------------------------------------------------------------------

# OpenCV: TG22 = (int)(0.4142135623730950488016887242097 * (1 << 15) + 0.5); a
# pixel is "horizontal" when |dy| << 15 < |dx| * TG22 and "vertical" when
# |dy| << 15 > |dx| * TG22 + (|dx| << 16). On a 0/1 image |dx|, |dy| <= 4, and on
# that range these two tests are exactly "12 |dy| < 5 |dx|" and "5 |dy| > 12 |dx|"
# (tests/test_chamfer.py checks all 3 x 3 neighbourhoods), which fit in int8.
CANNY_TG22 = 13573

# --- distance transform --------------------------------------------------------

UNIT_BITS = 24
"""Distances are integers in units of 2^-24 (exact for float32 weights < 2)."""
STEP_HV = 16022241
"""float32(0.955) * 2^24: OpenCV's horizontal/vertical step of DIST_L2, mask 3."""
STEP_DIAG = 22973042
"""float32(1.3693) * 2^24: OpenCV's diagonal step."""
_UNIT = 2.0 ** -UNIT_BITS

# Pixels per chunk of the CPU code paths (the ops are memory bound: a chunk's
# working set should stay in cache; the row sweeps prefer big batches).
_CANNY_CHUNK = 256
_DT_CHUNK = 2048


def _as_batch(images: torch.Tensor) -> tuple[torch.Tensor, tuple[int, ...]]:
    """(..., H, W) any dtype -> bool (N, H, W) and the leading shape."""
    if images.dim() < 2:
        raise ValueError(f"expected (..., H, W) images, got shape {tuple(images.shape)}")
    lead = tuple(images.shape[:-2])
    flat = images.reshape(-1, *images.shape[-2:])
    if flat.dtype != torch.bool:
        flat = flat != 0
    return flat, lead


def _canny_chunk(images: torch.Tensor) -> torch.Tensor:
    """bool (N, H, W) -> bool (N, H, W) edges of cv2.Canny(img * 255, 1, 3)."""
    x = images.to(torch.int8)
    # BORDER_REPLICATE padding -> xp (N, H+2, W+2)
    xp = torch.cat([x[:, :1], x, x[:, -1:]], dim=1)
    xp = torch.cat([xp[:, :, :1], xp, xp[:, :, -1:]], dim=2)
    # Sobel dx = [-1 0 1] across columns, smoothed [1 2 1] along rows; dy likewise.
    d = xp[:, :, 2:] - xp[:, :, :-2]  # (N, H+2, W)
    dx = d[:, :-2] + d[:, 2:]
    dx += d[:, 1:-1]
    dx += d[:, 1:-1]  # (N, H, W), values in [-4, 4]
    e = xp[:, 2:] - xp[:, :-2]  # (N, H, W+2)
    dy = e[:, :, :-2] + e[:, :, 2:]
    dy += e[:, :, 1:-1]
    dy += e[:, :, 1:-1]
    ax = dx.abs()
    ay = dy.abs()
    # L1 magnitude, zero outside the image (OpenCV's magnitude buffer border).
    mp = F.pad(ax + ay, (1, 1, 1, 1))  # (N, H+2, W+2)
    m = mp[:, 1:-1, 1:-1]
    horiz = ay * 12 < ax * 5
    vert = ay * 5 > ax * 12
    diag = ~(horiz | vert)
    # Each branch needs m > 0 implicitly: m > (a magnitude >= 0).
    edge = horiz & (m > mp[:, 1:-1, :-2]) & (m >= mp[:, 1:-1, 2:])
    edge |= vert & (m > mp[:, :-2, 1:-1]) & (m >= mp[:, 2:, 1:-1])
    # OpenCV: s = (dx ^ dy) < 0 ? -1 : 1, compare with (row-1, col-s) and
    # (row+1, col+s): same signs -> up-left / down-right, else up-right / down-left.
    same = (dx ^ dy) >= 0
    on_diag = same & (m > mp[:, :-2, :-2]) & (m > mp[:, 2:, 2:])
    on_diag |= ~same & (m > mp[:, :-2, 2:]) & (m > mp[:, 2:, :-2])
    edge |= diag & on_diag
    return edge


def canny_binary(images: torch.Tensor) -> torch.Tensor:
    """Edge maps of binary images, equal to ``cv2.Canny(img * 255, 1, 3) > 0``.

    images: (..., H, W), bool (any other dtype is read as ``!= 0``).
    Returns bool of the same shape.
    """
    flat, lead = _as_batch(images)
    if flat.shape[0] == 0:
        return flat.reshape(*lead, *flat.shape[-2:])
    chunk = _CANNY_CHUNK if flat.device.type == "cpu" else max(1, flat.shape[0])
    parts = [_canny_chunk(flat[i : i + chunk]) for i in range(0, flat.shape[0], chunk)]
    edges = parts[0] if len(parts) == 1 else torch.cat(parts)
    return edges.reshape(*lead, *flat.shape[-2:])


@dataclass(frozen=True)
class _UnitPlan:
    """Integer types and the "no edge" marker for an H x W distance transform."""

    px_dtype: torch.dtype  # horizontal pass, distances in pixels
    inf_px: int  # "no edge pixel in this row", in pixels
    unit_dtype: torch.dtype  # vertical sweeps, distances in 2^-24 units


def _unit_plan(height: int, width: int) -> _UnitPlan:
    # Largest finite chamfer distance in the image: at most max(H, W) - 1 steps,
    # each <= STEP_DIAG. The "no edge" value must exceed it after * STEP_HV.
    largest = (max(height, width) - 1) * STEP_DIAG
    inf_px = largest // STEP_HV + 1
    biggest_step = 1 << max(0, (width - 1).bit_length() - 1)  # the log-scan's last shift
    if inf_px + biggest_step <= 127:
        px_dtype = torch.int8
    elif inf_px + biggest_step <= 32767:
        px_dtype = torch.int16
    else:
        px_dtype = torch.int32
    # The sweeps add at most one STEP_DIAG to a value <= inf_px * STEP_HV.
    fits_int32 = inf_px * STEP_HV + STEP_DIAG < 2**31
    return _UnitPlan(px_dtype, inf_px, torch.int32 if fits_int32 else torch.int64)


def _row_distance_px(edges: torch.Tensor, plan: _UnitPlan) -> torch.Tensor:
    """Pixels to the nearest edge pixel of the same row (inf_px if none).

    edges: bool (..., W). A min-plus scan with shifts 1, 2, 4, ... in each
    direction (after the shifts 1..k every offset < 2k is covered).
    """
    width = edges.shape[-1]
    g = torch.full(edges.shape, plan.inf_px, dtype=plan.px_dtype, device=edges.device)
    g.masked_fill_(edges, 0)
    for forward in (True, False):
        k = 1
        while k < width:
            if forward:  # from the left: g[x] = min(g[x], g[x - k] + k)
                torch.minimum(g[..., k:], g[..., :-k] + k, out=g[..., k:])
            else:  # from the right: g[x] = min(g[x], g[x + k] + k)
                torch.minimum(g[..., :-k], g[..., k:] + k, out=g[..., :-k])
            k *= 2
    return g


def _sweep_rows(r: torch.Tensor) -> None:
    """In place: vertical and diagonal chamfer steps over rows, down then up.

    r: (H, N, W) integer distances in units; on entry the horizontal-only
    distances, on exit the full chamfer distance transform.
    """
    height, n, width = r.shape
    if width == 1:
        for rows in (range(1, height), range(height - 2, -1, -1)):
            for i in rows:
                prev = r[i - 1] if rows.step == 1 else r[i + 1]
                torch.minimum(r[i], prev + STEP_HV, out=r[i])
        return
    straight = torch.empty((n, width), dtype=r.dtype, device=r.device)
    diagonal = torch.empty((n, width - 1), dtype=r.dtype, device=r.device)
    for down in (True, False):
        rows = range(1, height) if down else range(height - 2, -1, -1)
        for i in rows:
            prev = r[i - 1] if down else r[i + 1]  # (N, W), already final for this sweep
            row = r[i]
            torch.add(prev, STEP_HV, out=straight)
            torch.minimum(row, straight, out=row)
            # diagonal[:, x] = min(prev[x], prev[x + 1]) + b serves row[x + 1] and row[x]
            torch.minimum(prev[:, :-1], prev[:, 1:], out=diagonal)
            diagonal += STEP_DIAG
            torch.minimum(row[:, 1:], diagonal, out=row[:, 1:])
            torch.minimum(row[:, :-1], diagonal, out=row[:, :-1])


def _distance_units_hnw(edges_hnw: torch.Tensor) -> torch.Tensor:
    """bool (H, N, W) edge maps -> (H, N, W) integer chamfer distances in units.

    Images without edge pixels get values >= inf_px * STEP_HV (not meaningful).
    """
    height, _, width = edges_hnw.shape
    plan = _unit_plan(height, width)
    px = _row_distance_px(edges_hnw, plan)
    r = px.to(plan.unit_dtype)
    r *= STEP_HV
    _sweep_rows(r)
    return r


def _distance_units(edges_hnw: torch.Tensor) -> torch.Tensor:
    """As _distance_units_hnw, chunked over N on the CPU to stay in cache."""
    n = edges_hnw.shape[1]
    chunk = _DT_CHUNK if edges_hnw.device.type == "cpu" else max(1, n)
    if n <= chunk:
        return _distance_units_hnw(edges_hnw)
    return torch.cat(
        [_distance_units_hnw(edges_hnw[:, i : i + chunk]) for i in range(0, n, chunk)], dim=1
    )


def distance_maps(edges: torch.Tensor) -> torch.Tensor:
    """Chamfer distance to the nearest edge pixel, as OpenCV computes it.

    edges: bool (..., H, W). Returns float32 (..., H, W) equal to
    ``cv2.distanceTransform((~edges).astype(uint8) * 255, cv2.DIST_L2, 3)`` up
    to OpenCV's own float32 rounding (we return the exact chamfer distance
    rounded once to float32; OpenCV 5 accumulates in float32, a few ulps off).
    Maps without any edge pixel are float32 max everywhere, like OpenCV's.
    """
    flat, lead = _as_batch(edges)
    n, height, width = flat.shape
    if n == 0:
        return torch.zeros(flat.shape, dtype=torch.float32, device=flat.device).reshape(
            *lead, height, width
        )
    units = _distance_units(flat.permute(1, 0, 2).contiguous())  # (H, N, W)
    dist = (units.permute(1, 0, 2).to(torch.float64) * _UNIT).to(torch.float32)
    empty = ~flat.flatten(1).any(1)
    dist[empty] = torch.finfo(torch.float32).max
    return dist.reshape(*lead, height, width)


# --- Chamfer distance -----------------------------------------------------------


def _edge_stats(edges_hnw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """bool (H, N, W) -> (edge pixel counts int64 (N,), degenerate bool (N,)).

    An image that is empty or full has no edges at all (its Sobel is zero with
    replicated borders), so "image or edge map empty or full" reduces to the
    edge count being 0 or H * W.
    """
    height, _, width = edges_hnw.shape
    counts = edges_hnw.sum(dim=(0, 2), dtype=torch.int64)
    return counts, (counts == 0) | (counts == height * width)


def _directed_term(dist_units: torch.Tensor, edges: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """sum(D * E) / (sum(E) + 1) with E in {0, 255}: float64 over the batch.

    dist_units, edges: (H, ..., W), broadcastable; counts: the edge counts of
    ``edges`` with the middle shape. The sum is exact in int64.
    """
    total = (dist_units * edges).sum(dim=(0, -1), dtype=torch.int64)
    return (total.to(torch.float64) * (255.0 * _UNIT)) / (counts.to(torch.float64) * 255.0 + 1.0)


def _check_pair_shapes(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape or pred.dim() < 2:
        raise ValueError(
            f"pred and target must be (..., H, W) of equal shape, got {tuple(pred.shape)} "
            f"and {tuple(target.shape)}"
        )


def chamfer(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CSGNet's CD of each pair: bool (..., H, W) x 2 -> float64 (...).

    Degenerate pairs (an image or an edge map empty or full) score PENALTY.
    Lower is better; 0 for an image against itself.
    """
    _check_pair_shapes(pred, target)
    p, lead = _as_batch(pred)
    t, _ = _as_batch(target.to(pred.device))
    n, height, width = p.shape
    out = torch.empty(n, dtype=torch.float64, device=p.device)
    chunk = _DT_CHUNK // 2 if p.device.type == "cpu" else max(1, n)
    for i in range(0, n, chunk):
        j = min(n, i + chunk)
        m = j - i
        # Both images of a pair go through Canny and the transform together:
        # (H, 2m, W) with the predictions first.
        edges = canny_binary(torch.cat([p[i:j], t[i:j]]))
        edges_hnw = edges.permute(1, 0, 2).contiguous()
        counts, degenerate = _edge_stats(edges_hnw)
        dist = _distance_units_hnw(edges_hnw)
        e_p, e_t = edges_hnw[:, :m], edges_hnw[:, m:]
        d_p, d_t = dist[:, :m], dist[:, m:]
        cd = (_directed_term(d_t, e_p, counts[:m]) + _directed_term(d_p, e_t, counts[m:])) / 2
        bad = degenerate[:m] | degenerate[m:]
        out[i:j] = torch.where(bad, torch.full_like(cd, PENALTY), cd)
    return out.reshape(lead)


@dataclass(frozen=True)
class TargetFeatures:
    """Edges and distance maps of N targets, computed once for many candidates.

    Fields (internal layout (H, N, W), rows of the whole batch contiguous):
      edges: bool (H, N, W) Canny edge maps
      dist: int (H, N, W) chamfer distance transforms in 2^-24 units
      counts: int64 (N,) edge pixel counts
      degenerate: bool (N,) target image or edge map empty or full
    Build with ``TargetFeatures.of(targets)``.
    """

    edges: torch.Tensor
    dist: torch.Tensor
    counts: torch.Tensor
    degenerate: torch.Tensor

    @staticmethod
    def of(targets: torch.Tensor) -> "TargetFeatures":
        """targets: bool (N, H, W)."""
        if targets.dim() != 3:
            raise ValueError(f"targets must be (N, H, W), got {tuple(targets.shape)}")
        t, _ = _as_batch(targets)
        edges_hnw = canny_binary(t).permute(1, 0, 2).contiguous()
        counts, degenerate = _edge_stats(edges_hnw)
        return TargetFeatures(edges_hnw, _distance_units(edges_hnw), counts, degenerate)

    def __len__(self) -> int:
        return self.edges.shape[1]

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the targets."""
        return self.edges.shape[0], self.edges.shape[2]

    def to(self, device: torch.device | str) -> "TargetFeatures":
        return TargetFeatures(*(x.to(device) for x in (self.edges, self.dist, self.counts, self.degenerate)))


def chamfer_against(pred: torch.Tensor, features: TargetFeatures) -> torch.Tensor:
    """CD of candidates against precomputed targets.

    pred: bool (N, K, H, W) -- K candidates for each of the N targets -- or
    (N, H, W), one candidate each. Returns float64 (N, K) or (N,), equal to
    ``chamfer(pred, targets[:, None].expand_as(pred))``.
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
    out = torch.empty((n, k), dtype=torch.float64, device=pred.device)
    # Chunk over targets so that a chunk holds about _DT_CHUNK candidates.
    per = max(1, _DT_CHUNK // max(1, k)) if pred.device.type == "cpu" else max(1, n)
    for i in range(0, n, per):
        j = min(n, i + per)
        m = j - i
        flat, _ = _as_batch(pred[i:j].reshape(m * k, height, width))
        e_p = canny_binary(flat).permute(1, 0, 2).contiguous()  # (H, m*K, W)
        counts_p, degenerate_p = _edge_stats(e_p)
        d_p = _distance_units_hnw(e_p)
        # Candidates as (H, m, K, W) against targets as (H, m, 1, W).
        e_p4 = e_p.view(height, m, k, width)
        d_p4 = d_p.view(height, m, k, width)
        e_t = features.edges[:, i:j, None]
        d_t = features.dist[:, i:j, None]
        counts_p = counts_p.view(m, k)
        cd = (
            _directed_term(d_t, e_p4, counts_p)
            + _directed_term(d_p4, e_t, features.counts[i:j, None].expand(m, k))
        ) / 2
        bad = degenerate_p.view(m, k) | features.degenerate[i:j, None]
        out[i:j] = torch.where(bad, torch.full_like(cd, PENALTY), cd)
    return out[:, 0] if single else out
