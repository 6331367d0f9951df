"""Wargus Figure 4 statistics: the content of ``metrics.json`` (paper §3.5.3;
docs/wargus-fig4.md#protocol-paper-351, which defines each key); curves from
:mod:`taskvar_torch.experiments.curves`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from taskvar_torch.config import METHODS  # tested side by side, in the paper's order
from taskvar_torch.experiments.curves import (
    final_count,
    moving_average,
    smoothing_window,
    trials_to_fraction,
    trials_to_fraction_of_max,
)
from taskvar_torch.experiments.results import code_version

EXPERIMENT = "wargus-fig4"  # metrics.json's "experiment" (a results folder's kind)


def mean_over_trials(items: np.ndarray, first: int | None = None) -> dict[str, float]:
    """Mean items per test episode over trials ``1..first`` (all: ``None``) of ``items`` ``(R,
    T)``: the mean, the standard deviation across repetitions and a 95% CI half-width
    (normal approximation over repetitions)."""
    per_rep = np.asarray(items, dtype=float)[:, :first].mean(1)  # (R,)
    R = per_rep.size
    std = float(per_rep.std(ddof=1)) if R > 1 else float("nan")
    return {
        "mean": float(per_rep.mean()),
        "std": std,
        "ci95": 1.959964 * std / math.sqrt(R) if R > 1 else float("nan"),
        "trials": int(np.asarray(items)[:, :first].shape[1]),
    }


def method_summary(
    items: np.ndarray,  # (R, T) mean items per test episode of one method
    inter: np.ndarray | None = None,  # (R, T) its interruptions per test episode
    item_lost: np.ndarray | None = None,  # (R, T) its item-lost events per test episode
) -> dict[str, Any]:
    """One method's entry of ``metrics.json``'s ``methods`` (definitions in the module docstring)
    from its per-repetition, per-trial scores; ``inter`` ``None``: a method that never interrupts
    (0), ``item_lost`` ``None``: not recorded."""
    items = np.asarray(items, dtype=float)
    R, T = items.shape
    nf = final_count(T)
    mean, std = items.mean(0), items.std(0)
    t90, reached = trials_to_fraction(mean)
    per_rep = [trials_to_fraction(items[r])[0] for r in range(R)]
    out = {
        "final_score": float(mean[-nf:].mean()),
        "final_score_std": float(items[:, -nf:].mean(1).std()),
        "trials_to_90pct": t90,
        "reached_90pct": reached,
        "trials_to_90pct_per_rep": per_rep,
        "trials_to_90pct_std": float(np.std(per_rep)),
        "trials_to_90pct_of_max": trials_to_fraction_of_max(mean),
        "mean_over_trials": mean_over_trials(items),
        "mean_first_250_trials": mean_over_trials(items, 250),
        "interruptions_per_episode": 0.0 if inter is None else float(np.mean(inter)),
        "curve_mean": mean.tolist(),
        "curve_std": std.tolist(),
        "curve_smoothed": moving_average(mean, smoothing_window(T)).tolist(),
        "curve_per_rep": items.tolist(),
    }
    if item_lost is not None:
        out["item_lost_per_episode"] = float(np.mean(item_lost))
    return out


def summarise(
    items: np.ndarray,  # (R, T, M) mean items per test episode
    inter: np.ndarray,  # (R, T, M) interruptions per test episode
    control: np.ndarray,  # (R, T, O) hierarchy steps per controlling subtask
    option_names: Sequence[str],
    option_depths: Sequence[int],
    item_lost: np.ndarray | None = None,  # (R, T, M) item_lost events per test episode
) -> dict[str, Any]:
    """``metrics.json``'s content from ``items``, ``inter`` and ``item_lost`` ``(R, T, M)`` (per
    test episode, per repetition, trial and method) and ``control`` ``(R, T, O)`` (the hierarchy's
    live test steps per subtask at depths ``option_depths``)."""
    R, T, M = items.shape
    nf = final_count(T)
    w = smoothing_window(T)
    methods = {}
    for m, name in enumerate(METHODS):
        lost = None if item_lost is None else item_lost[:, :, m]
        methods[name] = method_summary(items[:, :, m], inter[:, :, m], lost)

    def fractions(c: np.ndarray) -> dict[str, Any]:
        total = max(float(c.sum()), 1.0)
        per_option = {o: float(c[..., i].sum()) / total for i, o in enumerate(option_names)}
        per_level = {
            f"level_{d}": sum(v for v, dd in zip(per_option.values(), option_depths) if dd == d)
            for d in sorted(set(option_depths))
        }
        return {"per_subtask": per_option, "per_level": per_level, "steps": int(c.sum())}

    return {
        "experiment": EXPERIMENT,
        "code": code_version(),
        "methods": methods,
        "smoothing_window": w,
        "final_trials": nf,
        "definitions": {
            "score": "items collected per nominal test episode",
            "final_score": f"mean over repetitions of the last {nf} trials (10%)",
            "trials_to_90pct": f"first trial where the trailing {w}-trial moving average of the "
            "repetition-mean curve reaches 90% of final_score",
            "trials_to_90pct_of_max": f"first trial where the trailing {w}-trial moving average "
            "of the repetition-mean curve reaches 90% of its own maximum (the paper's bars)",
            "mean_over_trials": "mean items per test episode over all trials (std and 95% CI "
            "across repetitions); mean_first_250_trials: the same over trials 1-250",
            "hierarchy_trace": "fraction of the hierarchy's test steps each subtask (level 0: root "
            "TG+FE, level 1: components TG, FE) held control",
        },
        "hierarchy_trace": {
            "all_trials": fractions(control),
            "last_10pct": fractions(control[:, -nf:]),
        },
    }


__all__ = [
    "EXPERIMENT",
    "mean_over_trials",
    "method_summary",
    "summarise",
]
