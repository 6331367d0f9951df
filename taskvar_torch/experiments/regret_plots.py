"""Regret against the hidden parameter: each method's mean regret (95% CI) per group of episodes by
one hidden field of ``taskvar eval``'s ``episodes.csv`` (equal-count bins or values;
docs/evaluation.md); :func:`plot_regret` draws ``regret.png``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from taskvar_torch.experiments.evaluation import mean_ci95
from taskvar_torch.experiments.plots import pyplot, save_figure

PNG_NAME = "regret.png"
BINS = 8
"""Equal-count bins of a continuous hidden field."""


def _field(rows: Sequence[dict[str, Any]]) -> tuple[str, bool] | None:
    """The hidden field to group by, and whether it is continuous: the first ``instance_*`` field
    with more than ``BINS`` distinct values, else the first with more than one."""
    names = sorted({k for r in rows for k in r if k.startswith("instance_")})
    distinct = {n: len({r[n] for r in rows if n in r}) for n in names}
    for n in names:
        if distinct[n] > BINS:
            return n, True
    for n in names:
        if distinct[n] > 1:
            return n, False
    return None


def regret_by_instance(
    rows: Sequence[dict[str, Any]], methods: Sequence[str]
) -> dict[str, Any] | None:
    """Each method's mean regret (exact per-instance optimum minus its exact return, or its sampled
    return where it has no exact one) per group of the hidden field: ``{"field", "groups": [label,
    ...], "methods": {m: {"mean": [...], "ci95": [...], "sampled": bool}}}``; ``None`` without an
    optimum or a field that varies."""
    optimum = {r["episode"]: r["optimum_return"] for r in rows if "optimum_return" in r}
    field = _field(rows)
    if not optimum or field is None:
        return None
    name, continuous = field
    first = [r for r in rows if r["method"] == methods[0]]
    values = np.array([r[name] for r in first], dtype=np.float64)
    if continuous:
        edges = np.quantile(values, np.linspace(0.0, 1.0, BINS + 1))
        edges[-1] = np.nextafter(edges[-1], np.inf)
        labels = [f"{lo:.2f}-{hi:.2f}" for lo, hi in zip(edges[:-1], edges[1:])]
        group_of = {r["episode"]: int(np.searchsorted(edges, r[name], "right")) - 1 for r in first}
    else:
        kinds = sorted(set(values.tolist()))
        labels = [f"{v:g}" for v in kinds]
        group_of = {r["episode"]: kinds.index(float(r[name])) for r in first}
    out: dict[str, Any] = {"field": name[len("instance_") :], "groups": labels, "methods": {}}
    for m in methods:
        mine = [r for r in rows if r["method"] == m and r["episode"] in optimum]
        sampled = any("exact_return" not in r for r in mine)
        key = "return" if sampled else "exact_return"
        per = [[] for _ in labels]
        for r in mine:
            per[group_of[r["episode"]]].append(optimum[r["episode"]] - r[key])
        stats = [mean_ci95(torch.tensor(g, dtype=torch.float64)) if g else None for g in per]
        out["methods"][m] = {
            "mean": [None if s is None else float(s[0]) for s in stats],
            "ci95": [None if s is None else float(s[1]) for s in stats],
            "sampled": sampled,
        }
    return out


def plot_regret(data: dict[str, Any], path: Path, title: str) -> Path:
    """Each method's mean regret per group of the hidden field, with its 95% CI band."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    xs = np.arange(len(data["groups"]))
    for m, d in data["methods"].items():
        y = np.array([np.nan if v is None else v for v in d["mean"]])
        ci = np.array([np.nan if v is None else v for v in d["ci95"]])
        label = f"{m} (sampled)" if d["sampled"] else m
        (line,) = ax.plot(xs, y, marker="o", label=label)
        ax.fill_between(xs, y - ci, y + ci, alpha=0.2, color=line.get_color())
    ax.axhline(0.0, color="black", lw=0.8)
    ax.set_xticks(xs, data["groups"], rotation=30 if len(xs) > 4 else 0, fontsize=8)
    ax.set_xlabel(f"hidden {data['field']}")
    ax.set_ylabel("regret vs the per-instance optimum (95% CI)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


__all__ = ["BINS", "PNG_NAME", "plot_regret", "regret_by_instance"]
