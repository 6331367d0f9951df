"""Learning-curve statistics (paper §3.5.3's Figure 4 and any curve over trials): smoothing, the
"final" performance and the trials a curve takes to reach a fraction of it.
"""

from __future__ import annotations

import math

import numpy as np

FINAL_FRACTION = 0.1  # "final" performance: the mean of the last 10% of trials


def smoothing_window(trials: int) -> int:
    """Moving-average window: ``max(1, trials // 20)`` (25 for the paper's 500 trials)."""
    return max(1, int(trials) // 20)


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average along the last axis (the first values average what exists)."""
    x = np.asarray(x, dtype=float)
    c = np.cumsum(x, axis=-1)
    out = c.copy()
    out[..., window:] = c[..., window:] - c[..., :-window]
    n = np.minimum(np.arange(1, x.shape[-1] + 1), window)
    return out / n


def final_count(trials: int) -> int:
    """Number of last trials whose mean is the "final" performance: 10%, at least one."""
    return max(1, int(math.ceil(FINAL_FRACTION * trials)))


def trials_to_fraction_of_max(curve: np.ndarray, fraction: float = 0.9) -> int:
    """First trial (1-based) at which the smoothed ``curve`` reaches ``fraction`` of its own
    maximum (the paper's Figure 4 bars: "90% to their maximum performance")."""
    smooth = moving_average(np.asarray(curve, dtype=float), smoothing_window(np.size(curve)))
    return int(np.nonzero(smooth >= fraction * smooth.max())[0][0]) + 1


def trials_to_fraction(curve: np.ndarray, fraction: float = 0.9) -> tuple[int, bool]:
    """First trial (1-based) at which the smoothed ``curve`` reaches ``fraction`` of its final
    value (mean of the last 10% of the raw curve); ``(len(curve), False)`` if it never does."""
    curve = np.asarray(curve, dtype=float)
    final = curve[-final_count(curve.size) :].mean()
    smooth = moving_average(curve, smoothing_window(curve.size))
    hit = np.nonzero(smooth >= fraction * final)[0]
    return (int(hit[0]) + 1, True) if hit.size else (int(curve.size), False)


__all__ = [
    "FINAL_FRACTION",
    "final_count",
    "moving_average",
    "smoothing_window",
    "trials_to_fraction",
    "trials_to_fraction_of_max",
]
