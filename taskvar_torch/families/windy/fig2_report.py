"""Windy Figure 2 report: ``episodes.csv`` rows, the printed tables, and :func:`plot_results`, which
redraws the figures from a results folder alone (``taskvar plot DIR``; docs/windy-fig2.md).
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from taskvar_torch.config import load_config
from taskvar_torch.experiments.plots import plot_interruption_heatmap, plot_sorted_differences
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.config import section
from taskvar_torch.families.windy.family import windy_layout

CSV_NAME, METRICS_NAME = "episodes.csv", "metrics.json"
CSV_FIELDS = (
    "distribution", "run", "seed", "episode", "p", "direction", "start_row", "start_col",
    "return_averaging", "return_options", "return_interruption", "return_averaging_null",
    "interruptions", "exact_averaging", "exact_options", "exact_interruption",
)  # fmt: skip
FIGURES = {"train": "fig2_train.png", "south_only": "fig2_south_only.png"}
HEATMAP = "interruptions_heatmap.png"


def csv_rows(
    distribution: str,
    run: int,
    seed: int,
    base: dict[str, np.ndarray],
    cols: dict[str, np.ndarray],
    width: int,
) -> list[dict[str, Any]]:
    """``episodes.csv``'s rows (:data:`CSV_FIELDS`) of one run: per episode the instance and
    start cell of ``base`` (the averaging rollout; the same for every method) and every column of
    ``cols``; ``width`` is the grid's, to split the flat start cell into row and column."""
    rows = []
    start_row, start_col = np.divmod(base["start"], width)
    for i in range(start_row.size):
        row = {
            "distribution": distribution,
            "run": run,
            "seed": seed,
            "episode": i,
            "p": float(base["p"][i]),
            "direction": windy.DIRECTIONS[int(base["direction"][i])],
            "start_row": int(start_row[i]),
            "start_col": int(start_col[i]),
        }
        for k, v in cols.items():
            row[k] = v[i].item()
        rows.append(row)
    return rows


def format_start_table(rows: list[dict[str, Any]]) -> str:
    """The learnt averaging policy beside the oracle's optimum, per start cell."""
    lines = [
        "Averaging policy, exact expected 100-step return over the training distribution:",
        f"{'start':>8} {'oracle optimum':>15} {'learnt head':>12}",
    ]
    for r in rows:
        lines.append(f"{str(tuple(r['start'])):>8} {r['oracle_optimum']:15.3f} {r['learnt']:12.3f}")
    return "\n".join(lines)


def format_table(metrics: dict[str, Any]) -> str:
    """Sampled vs null vs exact, per distribution, as fixed-width text."""
    runs, eps = metrics.get("runs"), metrics.get("episodes_per_run")
    lines = [
        f"Windy Figure 2 (layout {metrics.get('layout')!r}, {runs} runs x {eps} episodes per "
        "distribution): return difference per paired episode",
        f"{'distribution':<12} {'comparison':<44} {'no worse':>9} {'better':>7} {'worse':>7} "
        f"{'mean diff +- CI95':>18}",
    ]

    def line(dist: str, name: str, s: dict[str, Any] | None) -> None:
        if s is None:
            lines.append(f"{dist:<12} {name:<44} {'n/a':>9}")
            return
        ci = s.get("mean_difference_ci95")
        ci_txt = "nan" if ci is None else f"{ci:.3f}"
        lines.append(
            f"{dist:<12} {name:<44} {s['fraction_no_worse']:9.1%} {s['fraction_better']:7.1%} "
            f"{s['fraction_worse']:7.1%} {s['mean_difference']:+9.3f} +- {ci_txt:<6}"
        )

    dists = (
        ("train", metrics),
        ("south_only", metrics.get("south_only")),
        ("heldout", metrics.get("heldout")),  # the sealed held-out seeds (training winds)
    )
    for dist, m in dists:
        if not m:
            continue
        line(dist, "interruption - averaging (sampled, paired)", m)
        line(dist, "null: averaging - averaging (indep. gusts)", m["null"])
        line(dist, "interruption - averaging (exact, learnt)", m.get("exact"))
        line(dist, "options - averaging (sampled, paired)", m["options_vs_averaging"])
        line(dist, "interruption - options (sampled, paired)", m["interruption_vs_options"])
        th = m.get("theorem1") or {}
        fired = th.get("firings", 0)
        prem = (
            f"Theorem 1 premise held at {th['premise_held_fraction']:.1%} of {fired} firings"
            if fired
            else "interruption never fired"
        )
        lines.append(
            f"{'':<12} interruptions/episode {m['interruptions_per_episode']:.3f} "
            f"(in {m['episodes_with_interruption']:.1%} of episodes); {prem}"
        )
    never = [
        d
        for d, m in dists
        if m
        and not (m.get("theorem1") or {}).get("firings", 0)
        and not m.get("interruptions_per_episode")
    ]
    if never:
        lines.append(
            f"Note ({', '.join(never)}): interruption never fired, so the interruption and options "
            "policies are identical there and a 0.000 difference with 100% no worse is a tie, not "
            "a gain; see docs/windy-fig2.md#what-the-numbers-say"
        )
    return "\n".join(lines)


def read_csv_columns(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """``{distribution: {column: array}}`` from ``episodes.csv``."""
    cols: dict[str, dict[str, list]] = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            d = cols.setdefault(row["distribution"], {})
            for k, v in row.items():
                d.setdefault(k, []).append(v)
    out: dict[str, dict[str, np.ndarray]] = {}
    for dist, d in cols.items():
        out[dist] = {}
        for k, v in d.items():
            try:
                out[dist][k] = np.array([float(x) if x != "" else np.nan for x in v])
            except ValueError:
                out[dist][k] = np.array(v)
    return out


def plot_results(out_dir: str | os.PathLike) -> list[Path]:
    """(Re)draw Figure 2 per distribution and the interruption heat-map from a results folder."""

    out = Path(out_dir)
    for name in (CSV_NAME, METRICS_NAME, "config.yaml"):
        if not (out / name).is_file():
            raise ValueError(f"{str(out)!r} is not a windy-fig2 results folder: {name} is missing")
    metrics = json.loads((out / METRICS_NAME).read_text())
    cfg = load_config(out / "config.yaml")
    cols = read_csv_columns(out / CSV_NAME)
    paths = []
    for dist, fname in FIGURES.items():
        c = cols.get(dist)
        if c is None:
            continue
        runs = sorted(set(c["run"].astype(int).tolist()))
        sel = [c["run"] == r for r in runs]
        diffs = [c["return_interruption"][s] - c["return_averaging"][s] for s in sel]
        nulls = [c["return_averaging"][s] - c["return_averaging_null"][s] for s in sel]
        exact = []
        if not np.isnan(c["exact_interruption"]).any():
            exact = [c["exact_interruption"][s] - c["exact_averaging"][s] for s in sel]
        label = "south-only test winds" if dist == "south_only" else "training distribution"
        paths.append(
            plot_sorted_differences(
                diffs,
                nulls,
                out / fname,
                title=f"Windy Figure 2 ({label}): interruption - averaging, {len(runs)} runs",
                exact_runs=exact,
            )
        )
    m_south = metrics.get("south_only") or {}
    paths.append(
        plot_interruption_heatmap(
            windy_layout(section(cfg)),
            {
                "training distribution": metrics.get("interruption_cells"),
                "south-only": m_south.get("interruption_cells"),
            },
            episodes={
                "training distribution": metrics.get("episodes"),
                "south-only": m_south.get("episodes"),
            },
            path=out / HEATMAP,
        )
    )
    return paths


__all__ = [
    "CSV_FIELDS",
    "CSV_NAME",
    "FIGURES",
    "HEATMAP",
    "METRICS_NAME",
    "csv_rows",
    "format_start_table",
    "format_table",
    "read_csv_columns",
    "plot_results",
]
