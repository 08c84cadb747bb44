"""Camera centres of two reconstructions compared up to a similarity (Umeyama 1991, in
float64): structure-from-motion recovers a scene only up to scale, rotation and translation,
so two runs agree when one set of centres maps onto the other by s R x + t. Written from the
paper, not with the library's alignment, so that it checks pycolmap independently."""

from __future__ import annotations

import numpy as np


def umeyama(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |b_i - (s R a_i + t)|^2 over points a, b: [N, 3]; R a proper rotation."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    mean_a, mean_b = a.mean(0), b.mean(0)
    da, db = a - mean_a, b - mean_b
    u, singular, vt = np.linalg.svd(db.T @ da / len(a))                   # the cross-covariance [3, 3]
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])              # no reflection
    rotation = u @ d @ vt
    scale = float(np.trace(np.diag(singular) @ d) / (da ** 2).sum(1).mean())
    return scale, rotation, mean_b - scale * rotation @ mean_a


def relative_residual(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance of b from the best similarity of a, over the RMS spread of b about its mean."""
    scale, rotation, translation = umeyama(a, b)
    residual = np.asarray(b, np.float64) - (scale * np.asarray(a, np.float64) @ rotation.T + translation)
    spread = np.asarray(b, np.float64) - np.asarray(b, np.float64).mean(0)
    return float(np.sqrt((residual ** 2).sum(1).mean() / (spread ** 2).sum(1).mean()))
