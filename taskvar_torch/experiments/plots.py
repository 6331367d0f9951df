"""Matplotlib figures of the experiments (PNG, written atomically)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 120) -> Path:
    """Save ``fig`` as PNG via a temporary file and a rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    os.replace(tmp, path)
    return path


def plot_sorted_differences(
    runs: Sequence[np.ndarray],
    null_runs: Sequence[np.ndarray],
    path: str | Path,
    title: str,
    label: str = "interruption - averaging",
) -> Path:
    """Paper Figure 2: per-episode return differences sorted ascending, one curve per run.

    ``null_runs`` (averaging against an independent rollout of itself, same instances and starts)
    are drawn dashed in grey: the spread that chance alone produces.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for i, d in enumerate(runs):
        d = np.sort(np.asarray(d, dtype=float))
        x = np.linspace(0, 1, d.size)
        ax.plot(x, d, lw=1.4, label=f"run {i + 1}" if len(runs) > 1 else label)
    for i, d in enumerate(null_runs):
        d = np.sort(np.asarray(d, dtype=float))
        ax.plot(np.linspace(0, 1, d.size), d, ls="--", lw=1.0, color="0.45",
                label="null: averaging - averaging (independent gusts)" if i == 0 else None)
    ax.axhline(0.0, color="black", lw=0.8)
    all_d = np.concatenate([np.asarray(d, dtype=float) for d in runs])
    frac = (all_d >= 0).mean()
    ax.axvline(1 - frac, color="tab:red", lw=0.8, ls=":")
    ax.text(1 - frac, ax.get_ylim()[1] * 0.9, f"  no worse: {frac:.1%}", color="tab:red", fontsize=9)
    ax.set_xlabel("episodes, sorted by difference (fraction)")
    ax.set_ylabel(f"return difference ({label})")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    out = save_figure(fig, path)
    plt.close(fig)
    return out
