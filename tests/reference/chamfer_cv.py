"""Per-pair reference of CSGNet's Chamfer distance, with OpenCV and numpy.

A direct transcription of CSGNet's ``chamfer`` (one pair at a time), kept
deliberately simple: the tests compare ``plad.metrics.chamfer`` against it and
``bench/metric.py`` uses it as the baseline. Needs ``cv2`` (tests only; the
library itself never imports OpenCV).
"""
from __future__ import annotations

import cv2
import numpy as np

PENALTY = 16.0


def canny_cv(image: np.ndarray) -> np.ndarray:
    """uint8 {0,255} edge map of a bool image, as CSGNet computes it."""
    return cv2.Canny(np.asarray(image, dtype=np.uint8) * 255, 1, 3)


def distance_cv(edges: np.ndarray) -> np.ndarray:
    """float32 distance map to the nearest edge pixel (3x3 chamfer mask)."""
    return cv2.distanceTransform(~edges, cv2.DIST_L2, 3)


def _degenerate(image: np.ndarray) -> bool:
    count = int(np.count_nonzero(image))
    return count == 0 or count == image.size


def chamfer_cv(pred: np.ndarray, target: np.ndarray) -> float:
    """CSGNet's CD between two bool (H, W) canvases; 16 for degenerate pairs."""
    pred = np.asarray(pred, dtype=bool)
    target = np.asarray(target, dtype=bool)
    if _degenerate(pred) or _degenerate(target):
        return PENALTY
    e_p = canny_cv(pred)
    e_t = canny_cv(target)
    if _degenerate(e_p) or _degenerate(e_t):
        return PENALTY
    d_p = distance_cv(e_p).astype(np.float64)
    d_t = distance_cv(e_t).astype(np.float64)
    e_p = e_p.astype(np.float64)
    e_t = e_t.astype(np.float64)
    term_p = np.sum(d_t * e_p) / (np.sum(e_p) + 1.0)
    term_t = np.sum(d_p * e_t) / (np.sum(e_t) + 1.0)
    return float((term_p + term_t) / 2.0)
