"""Wargus Figure 4 report: ``per_trial.csv`` rows, the printed table, and :func:`plot_results`,
which redraws ``fig4.png`` from a results folder alone (docs/wargus-fig4.md).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from taskvar_torch.config import METHODS
from taskvar_torch.experiments.curves import moving_average
from taskvar_torch.experiments.plots import pyplot, save_figure
from taskvar_torch.families.wargus.fig4_metrics import EXPERIMENT

CSV_FIELDS = ("rep", "trial", "method", "items", "interruptions")


def csv_rows(items: np.ndarray, inter: np.ndarray) -> list[dict[str, Any]]:
    """``per_trial.csv``'s rows (:data:`CSV_FIELDS`) from ``items`` and ``inter`` ``(R, T, M)``:
    one row per repetition, trial (1-based) and method."""
    R, T, M = items.shape
    return [
        {
            "rep": r,
            "trial": t + 1,
            "method": METHODS[m],
            "items": float(items[r, t, m]),
            "interruptions": float(inter[r, t, m]),
        }
        for r in range(R)
        for t in range(T)
        for m in range(M)
    ]


def format_table(metrics: dict[str, Any]) -> str:
    """Final score and trials-to-90% per method, the hierarchy's control split, the wall time."""
    p, tm = metrics.get("protocol", {}), metrics.get("timing", {})
    lines = [
        f"Wargus Figure 4: {p.get('repetitions')} repetitions x {p.get('trials')} trials "
        f"({p.get('learning_episodes_per_trial')} learning + {p.get('test_episodes_per_trial')} "
        f"nominal test episodes), grid {p.get('grid')}, horizon {p.get('horizon')}, "
        + (
            f"tau calibrated (root keeps {p.get('keep_share'):.0%} of no-conflict states)"
            if p.get("threshold") == "calibrated"
            else f"tau {p.get('tau')}"
        ),
        f"{'method':<14}{'final items':>12}{'+-std':>8}{'mean (all)':>12}{'90% final':>11}"
        f"{'90% max':>9}{'interr./ep':>12}",
    ]
    for name, m in metrics["methods"].items():
        t90 = f"{m['trials_to_90pct']}{'' if m['reached_90pct'] else '*'}"
        mean_all = m.get("mean_over_trials", {}).get("mean", float("nan"))
        lines.append(
            f"{name:<14}{m['final_score']:>12.3f}{m['final_score_std']:>8.3f}{mean_all:>12.3f}"
            f"{t90:>11}{m.get('trials_to_90pct_of_max', '-'):>9}"
            f"{m['interruptions_per_episode']:>12.2f}"
        )
    held = metrics.get("heldout")
    if held:  # the sealed held-out instances, beside the nominal seeds
        lines.append(
            f"held-out ({held['instances']['count']} sealed instances), mean items all trials / "
            "first half: "
            + ", ".join(
                f"{name} {m['mean_over_trials']['mean']:.3f} / {m['mean_first_half']['mean']:.3f}"
                for name, m in held["methods"].items()
            )
        )
    h = metrics["hierarchy_trace"]["all_trials"]["per_subtask"]
    lines.append("hierarchy control: " + ", ".join(f"{o} {v:.1%}" for o, v in h.items()))
    if "wall_seconds" in tm:
        lines.append(
            f"wall time {tm['wall_seconds']:.1f} s ({tm['seconds_per_trial']:.2f} s per trial); "
            "paper: hierarchy ~100 trials to 90%, averaging > 350"
        )
    if "cpu_seconds_per_trial" in tm:
        lines.append(
            "CPU s per trial: "
            + ", ".join(
                f"{k.replace('_', ' ')} {v:.3f}" for k, v in tm["cpu_seconds_per_trial"].items()
            )
            + f" (total {sum(tm['cpu_seconds_per_trial'].values()):.3f})"
        )
    for name, b in tm.get("baselines", {}).items():  # experiment.baselines: their own agents
        lines.append(
            f"{name} agent: CPU s per trial "
            + ", ".join(
                f"{k.replace('_', ' ')} {v:.3f}" for k, v in b["cpu_seconds_per_trial"].items()
            )
            + f" (total {sum(b['cpu_seconds_per_trial'].values()):.3f}), wall {b['wall_seconds']:.1f} s"
        )
    return "\n".join(lines)


STYLES = {
    "hierarchy": dict(color="tab:blue", ls="-"),
    "averaging": dict(color="tab:green", ls="--"),
    "options": dict(color="tab:orange", ls=":"),
    "interruption": dict(color="tab:red", ls="-."),
    "recurrent": dict(color="tab:purple", ls=(0, (5, 1, 1, 1, 1, 1))),  # experiment.baselines
}


def is_results_folder(out_dir: str | os.PathLike) -> bool:
    """Whether ``out_dir`` holds a ``metrics.json`` written by :func:`wargus_fig4`."""
    path = Path(out_dir) / "metrics.json"
    try:
        return json.loads(path.read_text()).get("experiment") == EXPERIMENT
    except (OSError, ValueError, AttributeError):
        return False


def plot_results(out_dir: str | os.PathLike) -> list[Path]:
    """(Re)draw ``fig4.png`` from ``metrics.json``: smoothed mean items per test episode per trial
    with +-std bands over repetitions, and the trials-to-90% bars (paper Figure 4 layout)."""

    out = Path(out_dir)
    metrics = json.loads((out / "metrics.json").read_text())
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(
        2, 1, figsize=(8, 6), gridspec_kw={"height_ratios": [3, 1]}, sharex=True
    )
    w = metrics["smoothing_window"]
    for name, m in metrics["methods"].items():
        mean = np.asarray(m["curve_smoothed"], dtype=float)
        std = moving_average(np.asarray(m["curve_std"], dtype=float), w)
        x = np.arange(1, mean.size + 1)
        ax.plot(x, mean, lw=1.6, label=name, **STYLES.get(name, {}))
        ax.fill_between(
            x, mean - std, mean + std, alpha=0.15, color=STYLES.get(name, {}).get("color")
        )
    ax.set_ylabel("items per test episode")
    ax.set_title(
        f"Wargus lifelong protocol: mean of {metrics['protocol']['repetitions']} repetitions "
        f"(moving average of {w} trials, bands: std)"
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    names = list(metrics["methods"])
    t90 = [metrics["methods"][n]["trials_to_90pct"] for n in names]
    err = [metrics["methods"][n]["trials_to_90pct_std"] for n in names]
    bx.barh(names, t90, xerr=err, color=[STYLES.get(n, {}).get("color") for n in names], alpha=0.7)
    bx.set_xlabel("trial")
    bx.set_title(
        "trials to 90% of final performance (error bars: std over repetitions)", fontsize=9
    )
    bx.grid(alpha=0.3, axis="x")
    path = save_figure(fig, out / "fig4.png")
    plt.close(fig)
    return [path]


__all__ = ["CSV_FIELDS", "STYLES", "csv_rows", "format_table", "is_results_folder", "plot_results"]
