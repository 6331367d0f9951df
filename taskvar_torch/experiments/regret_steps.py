"""Regret against the step within the episode (docs/evaluation.md): each step's instantaneous regret
``V*_{H-t}(s_t) - Q*_{H-t}(s_t, a_t)`` from the family's oracle (``step_regret``), averaged per step
(:func:`regret_by_step`) and drawn (:func:`plot_regret_by_step`, ``regret_by_step.png``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from taskvar_torch.experiments.evaluation import mean_ci95
from taskvar_torch.experiments.plots import pyplot, save_figure

PNG_NAME = "regret_by_step.png"
TAIL = 0.01
"""The plot's x axis stops where fewer than this fraction of every method's episodes still play."""


def supports_step_regret(oracle: Any) -> bool:
    """Whether ``oracle`` gives per-step regret (``step_regret``: windy's and Taxi's)."""
    return oracle is not None and callable(getattr(oracle, "step_regret", None))


def step_regret_affordable(oracle: Any, instance: Mapping[str, np.ndarray]) -> bool:
    """Whether per-step regret of these episodes is cheap: the oracle's ``step_solves`` (its
    backward inductions, one per distinct instance for Taxi) within its ``max_step_solves`` (no
    such attribute, as windy's: always). ``taskvar eval --exact`` computes it anyway."""
    limit = getattr(oracle, "max_step_solves", None)
    if limit is None:
        return True
    fields = [np.asarray(instance[k]) for k in oracle.instance_keys]
    return int(oracle.step_solves(*fields)) <= int(limit)


def episode_step_regret(
    oracle: Any,
    instance: Mapping[str, np.ndarray],
    cells: np.ndarray,
    actions: np.ndarray,
    alive: np.ndarray,
    chunk: int = 2000,
) -> np.ndarray:
    """``(N, T)`` instantaneous regret of each episode's actions under its own instance (the
    ``oracle.instance_keys`` fields of ``instance``), 0 after the episode ended."""
    names = tuple(oracle.instance_keys)
    missing = [k for k in names if k not in instance]
    if missing:
        raise ValueError(f"per-step regret needs the episodes' instance fields {list(names)}")
    out = []
    for lo in range(0, len(cells), chunk):
        sl = slice(lo, lo + chunk)
        fields = []
        for k in names:
            v = torch.as_tensor(np.asarray(instance[k])[sl])
            fields.append(v.to(torch.float64) if v.is_floating_point() else v.to(torch.int64))
        gap = oracle.step_regret(*fields, cells[sl], actions[sl], alive[sl])
        out.append(gap.cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, cells.shape[1]))


def regret_by_step(per_method: Mapping[str, np.ndarray], alive: Mapping[str, np.ndarray]) -> dict:
    """Per method, from its ``(N, T)`` step regrets and live masks: ``{"steps": T, "methods": {m:
    {"mean", "ci95", "live", "live_mean", "total"}}}``.

    ``mean[t]`` averages step ``t`` over all episodes (an ended one adds 0), so ``total`` is the
    method's regret; ``live[t]`` is the fraction still playing, ``live_mean[t]`` their mean regret.
    """
    T = 0
    for a in alive.values():
        steps = np.flatnonzero(np.asarray(a).any(0))
        T = max(T, int(steps[-1]) + 1 if steps.size else 0)
    out: dict[str, Any] = {"steps": T, "methods": {}}
    for m, gap in per_method.items():
        g = np.asarray(gap, dtype=np.float64)[:, :T]
        live = np.asarray(alive[m], dtype=bool)[:, :T]
        if g.shape[1] < T:  # a method whose episodes all ended earlier than another's
            g = np.pad(g, ((0, 0), (0, T - g.shape[1])))
            live = np.pad(live, ((0, 0), (0, T - live.shape[1])))
        stats = [mean_ci95(torch.as_tensor(g[:, t])) for t in range(T)]
        n_live = live.sum(0)
        out["methods"][m] = {
            "mean": [float(s[0]) for s in stats],
            "ci95": [float(s[1]) for s in stats],
            "live": (n_live / max(len(g), 1)).tolist(),
            "live_mean": [float(g[live[:, t], t].mean()) if n_live[t] else None for t in range(T)],
            "total": float(g.sum(1).mean()) if len(g) else 0.0,
        }
    return out


def plot_regret_by_step(data: Mapping[str, Any], path: Path, title: str) -> Path:
    """Two panels against the step: each method's mean regret per step over all episodes with its
    95% CI band (the area under a line is the method's regret), and the fraction of episodes still
    playing."""
    plt = pyplot()
    fig, (ax, live_ax) = plt.subplots(
        2, 1, figsize=(6.4, 5.2), sharex=True, gridspec_kw={"height_ratios": [3, 1.4]}
    )
    xs = np.arange(data["steps"])
    xlabel = "step t within the episode"
    for m, d in data["methods"].items():
        y, ci = np.array(d["mean"]), np.array(d["ci95"])
        (line,) = ax.plot(xs, y, marker=".", label=f"{m} (sum {d['total']:.2f})")
        ax.fill_between(xs, y - ci, y + ci, alpha=0.2, color=line.get_color())
        live_ax.plot(xs, d["live"], color=line.get_color())
    ax.axhline(0.0, color="black", lw=0.8)
    live = np.array([d["live"] for d in data["methods"].values()]).max(0)
    shown = np.flatnonzero(live >= TAIL)
    if shown.size and shown[-1] + 1 < len(xs):  # the long tail of a few trapped episodes
        live_ax.set_xlim(-0.5, shown[-1] + 1.5)
        xlabel += f" (to step {shown[-1] + 1}: {1 - TAIL:.0%} of episodes ended; sums: all steps)"
    ax.set_ylabel("regret at step t (95% CI)\nmean over all episodes")
    ax.set_title(title)
    ax.legend(fontsize=8)
    live_ax.set_ylabel("episodes\nstill playing")
    live_ax.set_ylim(0.0, 1.02)
    live_ax.set_xlabel(xlabel, fontsize=8 if "ended" in xlabel else None)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


__all__ = [
    "PNG_NAME",
    "episode_step_regret",
    "plot_regret_by_step",
    "regret_by_step",
    "supports_step_regret",
]
