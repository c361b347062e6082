"""Residual statistics in the style of the seed's Table 1, and hold-out splits."""

from __future__ import annotations

import numpy as np

AXES = ("x", "y", "z")


def axis_statistics(errors: np.ndarray) -> dict[str, dict[str, float]]:
    """Per axis of ``errors`` (n, 3): mean absolute, RMS and maximum absolute error (mm)."""
    e = np.abs(np.asarray(errors, dtype=float))
    return {
        axis: {
            "mean_abs": float(e[:, k].mean()) if len(e) else float("nan"),
            "rms": float(np.sqrt(np.mean(e[:, k] ** 2))) if len(e) else float("nan"),
            "max": float(e[:, k].max()) if len(e) else float("nan"),
        }
        for k, axis in enumerate(AXES)
    }


def holdout_split(n: int, fraction: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random split of ``range(n)`` into sorted (fit, hold-out) index arrays."""
    n_hold = round(fraction * n)
    order = np.random.default_rng(seed).permutation(n)
    return np.sort(order[n_hold:]), np.sort(order[:n_hold])
