"""Matplotlib figures of the experiments (PNG, written atomically)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def pyplot():
    """pyplot, headless (Agg) in scripts and the CLI; a notebook keeps its inline backend."""
    # imported here: the backend must be chosen before pyplot is first imported
    import sys

    import matplotlib

    if "ipykernel" not in sys.modules:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 120) -> Path:
    """Save ``fig`` as PNG via a temporary file and a rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    try:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.filename is None and e.errno is not None:
            e.filename = str(path)  # a full disk's write names no file: the CLI's line names it
        raise
    return path


def plot_sorted_differences(
    runs: Sequence[np.ndarray],
    null_runs: Sequence[np.ndarray],
    path: str | Path,
    title: str,
    label: str = "interruption - averaging",
    exact_runs: Sequence[np.ndarray] = (),
) -> Path:
    """Paper Figure 2: per-episode return differences sorted ascending, one curve per run;
    ``null_runs`` dashed grey (chance alone), ``exact_runs`` dotted black.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for i, d in enumerate(runs):
        d = np.sort(np.asarray(d, dtype=float))
        x = np.linspace(0, 1, d.size)
        ax.plot(x, d, lw=1.4, label=f"run {i + 1}" if len(runs) > 1 else label)
    for i, d in enumerate(null_runs):
        d = np.sort(np.asarray(d, dtype=float))
        ax.plot(
            np.linspace(0, 1, d.size),
            d,
            ls="--",
            lw=1.0,
            color="0.45",
            label="null: averaging - averaging (independent gusts)" if i == 0 else None,
        )
    for i, d in enumerate(exact_runs):
        d = np.sort(np.asarray(d, dtype=float))
        ax.plot(
            np.linspace(0, 1, d.size),
            d,
            ls=":",
            lw=1.3,
            color="black",
            label="exact (oracle): expected-return difference" if i == 0 else None,
        )
    ax.axhline(0.0, color="black", lw=0.8)
    all_d = np.concatenate([np.asarray(d, dtype=float) for d in runs])
    frac = (all_d >= 0).mean()
    ax.axvline(1 - frac, color="tab:red", lw=0.8, ls=":")
    note = f"no worse: {frac:.1%}"
    if len(null_runs):
        note += (
            f"\nnull: {(np.concatenate([np.asarray(d, float) for d in null_runs]) >= 0).mean():.1%}"
        )
    if len(exact_runs):
        ex = np.concatenate([np.asarray(d, float) for d in exact_runs])
        note += f"\nexact: {(ex >= -1e-9).mean():.1%}"
    ax.text(
        0.02,
        0.97,
        note,
        transform=ax.transAxes,
        va="top",
        color="tab:red",
        fontsize=9,
        bbox=dict(fc="white", ec="none", alpha=0.8),
    )
    ax.set_xlabel("episodes, sorted by difference (fraction)")
    ax.set_ylabel(f"return difference ({label})")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def plot_interruption_heatmap(
    layout,
    counts: dict[str, Sequence[int] | None],
    episodes: dict[str, int | None],
    path: str | Path,
) -> Path:
    """Where offline interruption fired (paper §3.3, Algorithm 1 line 6): firings per episode per
    cell, one panel per test distribution, on the grid (walls hatched, goals outlined)."""
    plt = pyplot()
    panels = [(k, v) for k, v in counts.items() if v is not None]
    fig, axes = plt.subplots(
        1,
        max(len(panels), 1),
        figsize=(5.0 * max(len(panels), 1), 4.4),
        squeeze=False,
        layout="constrained",
    )
    H, W = layout.height, layout.width
    grids = {
        k: np.asarray(v, dtype=float).reshape(H, W) / max(int(episodes.get(k) or 1), 1)
        for k, v in panels
    }
    vmax = max([g.max() for g in grids.values()] + [1e-3])  # one colour scale for every panel
    for ax, (name, cnt) in zip(axes[0], panels):
        n = max(int(episodes.get(name) or 1), 1)
        grid = grids[name]
        masked = np.ma.masked_where(
            np.array([[ch in "#G" for ch in row] for row in layout.rows]), grid
        )
        im = ax.imshow(masked, cmap="Reds", vmin=0, vmax=vmax)
        for r in range(H):
            for c in range(W):
                ch = layout.rows[r][c]
                if ch == "#":
                    ax.add_patch(plt.Rectangle((c - 0.5, r - 0.5), 1, 1, color="0.3"))
                elif ch == "G":
                    ax.add_patch(
                        plt.Rectangle(
                            (c - 0.5, r - 0.5),
                            1,
                            1,
                            fill=False,
                            hatch="//",
                            color="tab:green",
                            lw=0.5,
                        )
                    )
                elif H * W <= 100:
                    ax.text(
                        c,
                        r,
                        f"{ch}\n{grid[r, c]:.3f}" if ch != "." else f"{grid[r, c]:.3f}",
                        ha="center",
                        va="center",
                        fontsize=7,
                        bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.7),
                    )
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{name}\n(total {int(np.sum(cnt))} firings, {n} episodes)", fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8, label="firings per episode")
    fig.suptitle("Where offline interruption fired (row 0 = north)", fontsize=10)
    out = save_figure(fig, path)
    plt.close(fig)
    return out
