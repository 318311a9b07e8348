"""Uncertainty of the fitted parameters: the Gauss-Newton covariance of their logarithms."""

from __future__ import annotations

import numpy as np


def gauss_newton_covariance(jac: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, float]:
    """``s^2 (J^T J)^-1`` with ``s^2 = ||r||^2 / (m - p)`` (p parameters).

    With m = p there are no degrees of freedom left to estimate s^2; the weights are then
    taken as exact inverse standard deviations (s^2 = 1). A singular J^T J (a parameter the
    target does not see) gives infinite variances.
    """
    m, p = jac.shape
    s2 = float(r @ r / (m - p)) if m > p else 1.0
    jtj = jac.T @ jac
    if not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e14:
        return np.full((p, p), np.inf), s2
    return s2 * np.linalg.inv(jtj), s2
