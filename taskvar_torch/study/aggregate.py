"""Many-seed statistics with ``rliable`` (Agarwal et al., 2021): what ``taskvar report`` quotes
(docs/claims.md).

Scores are ``{method: array (runs, tasks)}``, one row per training seed. :func:`interval_estimates`
(IQM and mean with stratified-bootstrap 95% CIs), :func:`paired_differences` (the same on paired
per-seed differences), :func:`probability_of_improvement` and :func:`performance_profile` are
rliable's. ``rliable`` is imported on first use; bootstraps are seeded (:func:`_seeded`).
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np

REPS = 2000
"""Bootstrap replications (rliable's own default for performance profiles)."""


def _rliable() -> tuple[Any, Any]:
    from rliable import library, metrics

    return library, metrics


@contextlib.contextmanager
def _seeded(seed: int) -> Iterator[None]:
    """rliable's stratified bootstrap draws its resamples from NumPy's *global* stream
    (``np.random.choice``), whatever ``random_state`` says: seed it here and give the caller's
    state back after; arch's deprecation notice of ``random_state`` is silenced."""
    state = np.random.get_state()
    np.random.seed(int(seed))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            yield
    finally:
        np.random.set_state(state)


def _matrix(x: Any) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] < 1:
        raise ValueError(f"scores must be (runs, tasks), got shape {a.shape}")
    return a


def interval_estimates(
    scores: Mapping[str, Any], reps: int = REPS, seed: int = 0
) -> dict[str, dict[str, Any]]:
    """IQM and mean of each entry's ``(runs, tasks)`` scores with stratified-bootstrap 95% CIs:
    ``{key: {"iqm", "iqm_ci95": [lo, hi], "mean", "mean_ci95": [lo, hi], "runs", "tasks"}}``."""
    library, metrics = _rliable()
    mats = {k: _matrix(v) for k, v in scores.items()}

    def func(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_mean(x)])

    with _seeded(seed):
        point, ci = library.get_interval_estimates(
            mats, func, reps=int(reps), random_state=np.random.RandomState(seed)
        )
    return {
        k: {
            "iqm": float(point[k][0]),
            "iqm_ci95": [float(ci[k][0, 0]), float(ci[k][1, 0])],
            "mean": float(point[k][1]),
            "mean_ci95": [float(ci[k][0, 1]), float(ci[k][1, 1])],
            "runs": int(mats[k].shape[0]),
            "tasks": int(mats[k].shape[1]),
        }
        for k in mats
    }


def paired_differences(
    scores: Mapping[str, Any],
    pairs: Sequence[tuple[str, str]],
    reps: int = REPS,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """:func:`interval_estimates` of ``scores[a] - scores[b]`` per seed for each ``(a, b)`` in
    ``pairs`` (keys ``"a - b"``): row ``i`` of both is the same seed's, on the same episodes."""
    diffs = {}
    for a, b in pairs:
        x, y = _matrix(scores[a]), _matrix(scores[b])
        if x.shape != y.shape:
            raise ValueError(
                f"paired scores must have the same shape: {a} {x.shape}, {b} {y.shape}"
            )
        diffs[f"{a} - {b}"] = x - y
    return interval_estimates(diffs, reps, seed)


def probability_of_improvement(
    scores: Mapping[str, Any], base: str, reps: int = REPS, seed: int = 0
) -> dict[str, dict[str, Any]]:
    """rliable's probability that each method improves on ``base`` with its 95% CI (unpaired, as
    rliable defines it): ``{method: {"probability", "ci95": [lo, hi]}}``.
    """
    library, metrics = _rliable()
    y = _matrix(scores[base])
    data = {m: (_matrix(v), y) for m, v in scores.items() if m != base}

    def func(x: np.ndarray, yy: np.ndarray) -> np.ndarray:
        return np.array([metrics.probability_of_improvement(x, yy)])

    with _seeded(seed):
        point, ci = library.get_interval_estimates(
            data, func, reps=int(reps), random_state=np.random.RandomState(seed)
        )
    return {
        m: {"probability": float(point[m][0]), "ci95": [float(ci[m][0, 0]), float(ci[m][1, 0])]}
        for m in data
    }


def performance_profile(
    scores: Mapping[str, Any], taus: Sequence[float], reps: int = REPS, seed: int = 0
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """rliable's score distributions: for each method the fraction of (seed, task) scores above
    each ``tau``, with bootstrap 95% bands (``library.create_performance_profile``)."""
    library, _ = _rliable()
    mats = {k: _matrix(v) for k, v in scores.items()}
    with _seeded(seed):
        return library.create_performance_profile(
            mats, np.asarray(taus, dtype=float), reps=int(reps)
        )


def plot_performance_profiles(
    ax: Any,
    profiles: Mapping[str, np.ndarray],
    cis: Mapping[str, np.ndarray],
    taus: Sequence[float],
    xlabel: str,
) -> None:
    """Draw :func:`performance_profile`'s curves and bands on ``ax`` (``rliable.plot_utils``)."""
    from rliable import plot_utils

    plot_utils.plot_performance_profiles(
        dict(profiles),
        np.asarray(taus, dtype=float),
        performance_profile_cis=dict(cis),
        ax=ax,
        xlabel=xlabel,
        ylabel="fraction of seeds' scores > tau",
        labelsize="small",
        ticklabelsize="small",
    )
    ax.legend(fontsize=7, loc="upper right")


__all__ = [
    "REPS",
    "interval_estimates",
    "paired_differences",
    "performance_profile",
    "plot_performance_profiles",
    "probability_of_improvement",
]
