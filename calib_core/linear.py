"""The seed's linear solution: ``H = R-bar^+ S`` (eq 8, 13-14)."""

from __future__ import annotations

import numpy as np


def linear_solution(regressor: np.ndarray, observation: np.ndarray) -> np.ndarray:
    """Least-squares ``H`` of the stacked system ``S = R-bar H`` (eq 13-14).

    ``regressor`` is (n, 3, p), ``observation`` (n, 3); the Moore-Penrose solution is computed by
    ``numpy.linalg.lstsq`` (an SVD), which equals ``pinv(R-bar) @ S`` without forming the pseudo-
    inverse.
    """
    p = regressor.shape[2]
    h, *_ = np.linalg.lstsq(regressor.reshape(-1, p), observation.reshape(-1), rcond=None)
    return h
