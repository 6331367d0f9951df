"""Scaled-up grids report: ``scale.csv`` rows, the printed table and ``scale.png`` from a results
folder's ``metrics.json`` (docs/scale.md; ``taskvar plot DIR``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from taskvar_torch.config import METHODS
from taskvar_torch.experiments.plots import pyplot, save_figure

EXPERIMENT = "scale"
"""``metrics.json``'s ``"experiment"`` (a results folder's kind)."""
CSV_NAME, METRICS_NAME, FIGURE = "scale.csv", "metrics.json", "scale.png"
CURVES_FIGURE = "scale_curves.png"
CSV_FIELDS = (
    "case", "family", "grid_side", "cells", "num_envs", "frames", "updates", "frames_per_batch",
    "updates_per_batch", "train_seconds", "frames_per_second", "method", "mean_return", "ci95",
    "gap_closed", "random_return", "oracle_return", "interruptions_per_episode", "peak_rss_mb",
)  # fmt: skip
SEED_FIELD = "seed"
"""``scale.csv``'s column of the training seed, after ``num_envs``: only with ``seeds`` > 1."""


def report_methods(metrics: dict[str, Any]) -> tuple[str, ...]:
    """The methods of the rows and columns: the paper's (:data:`METHODS`), then the baselines
    the run trained (``metrics["baselines"]``, docs/scale.md#baselines), where it has any."""
    return (*METHODS, *metrics.get("baselines", ()))


def csv_fields(metrics: dict[str, Any]) -> tuple[str, ...]:
    """``scale.csv``'s columns: :data:`CSV_FIELDS`, with :data:`SEED_FIELD` after ``num_envs``
    when the cells hold several seeds (``per_seed``)."""
    if not any(c.get("per_seed") for c in metrics["cells"]):
        return CSV_FIELDS
    i = CSV_FIELDS.index("num_envs") + 1
    return (*CSV_FIELDS[:i], SEED_FIELD, *CSV_FIELDS[i:])


def csv_rows(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per (cell, method), references in every row; a cell with several seeds
    (``per_seed``) gives one row per (cell, seed, method) with its ``seed``; the baselines' rows
    follow the methods' (:func:`report_methods`)."""
    rows = []
    for c in metrics["cells"]:
        ref = metrics["references"][c["case"]]
        orc = ref["oracle_averaging"]
        runs = c.get("per_seed") or [{"seed": None, "methods": c["methods"]}]
        for run, m in ((run, m) for run in runs for m in report_methods(metrics)):
            r = run["methods"].get(m)
            row = {k: c[k] for k in CSV_FIELDS if k in c}
            if run["seed"] is not None:
                row[SEED_FIELD] = run["seed"]
            row.update(
                method=m,
                random_return=ref["random"]["mean_return"],
                oracle_return=orc["mean_return"] if orc else "",
            )
            if r is None:
                row["mean_return"] = "n/a"
            else:
                row.update(
                    mean_return=r["mean_return"],
                    ci95=r["ci95"],
                    gap_closed="" if r.get("gap_closed") is None else r["gap_closed"],
                    interruptions_per_episode=r.get("interruptions_per_episode", ""),
                )
            rows.append(row)
    return rows


# --------------------------------------------------------------------------------------------
# table and figure


def format_table(metrics: dict[str, Any]) -> str:
    """One line per cell: time, frames/s, each method's mean return (CI) (the baselines' after
    the methods', where trained: :func:`report_methods`), the references."""
    methods = report_methods(metrics)
    budgets = sorted({int(c["frames"]) for c in metrics["cells"]}) or [metrics["total_frames"]]
    frames = (
        f"{budgets[0]} training frames per cell"
        if len(budgets) == 1
        else f"{budgets[0]}-{budgets[-1]} training frames per cell (column 'frames')"
    )
    lines = [
        f"Scaled-up grids: {frames}, "
        f"{metrics['eval_episodes']} test episodes per method "
        "per cell: mean return +- 95% CI (windy: -steps, and in brackets the gap closed, "
        "(R - random) / (oracle - random); Wargus: items per episode)",
        f"{'case':<14} {'N':>5} {'frames':>8} {'updates':>7} {'train s':>8} {'frames/s':>9} "
        f"{'peak MB':>7} "
        + " ".join(f"{m:>21}" for m in methods)
        + f" {'random':>8} {'oracle':>8}",
    ]
    for c in metrics["cells"]:
        ref = metrics["references"][c["case"]]
        cols = []
        for m in methods:
            r = c["methods"].get(m)
            if r is None:
                cols.append(f"{'n/a':>21}")
                continue
            gap = r.get("gap_closed")
            txt = f"{r['mean_return']:.2f}+-{_ci(r['ci95'])}"
            txt += f" ({gap:.2f})" if gap is not None else ""
            cols.append(f"{txt:>21}")
        orc = ref["oracle_averaging"]
        lines.append(
            f"{c['case']:<14} {c['num_envs']:>5} {c['frames']:>8} {c['updates']:>7} "
            f"{c['train_seconds']:8.1f} "
            f"{c['frames_per_second'] or 0:9.0f} {c.get('peak_rss_mb') or 0:7.0f} "
            + " ".join(cols)
            + f" {ref['random']['mean_return']:8.2f} "
            + (f"{orc['mean_return']:8.2f}" if orc else f"{'n/a':>8}")
        )
    lines += format_seeds(metrics)
    lines += format_heldout(metrics)
    lines += format_heads(metrics)
    lines.append(f"wall time {metrics['wall_seconds']:.0f} s, {metrics['threads']} torch thread(s)")
    return "\n".join(lines)


def format_seeds(metrics: dict[str, Any]) -> list[str]:
    """Lines of each cell's aggregate over its training seeds (``over_seeds``; cells with one
    seed have none): each method's mean return over the seeds with its 95% CI [lo, hi] (rliable's
    stratified bootstrap) and, in brackets, the gap closed by the mean."""
    cells = [c for c in metrics["cells"] if c.get("over_seeds")]
    if not cells:
        return []
    lines = [
        "Over the training seeds (the table above is the first seed's run): each method's mean "
        "return over the seeds [95% CI of that mean, stratified bootstrap] (gap closed)"
    ]
    for c in cells:
        seeds = c["seeds"]
        parts = []
        for m in report_methods(metrics):
            r = c["over_seeds"].get(m)
            if r is None:
                parts.append(f"{m} n/a")
                continue
            lo, hi = r["mean_ci95"]
            gap = "" if r["gap_closed"] is None else f" ({r['gap_closed']:.2f})"
            parts.append(f"{m} {r['mean_return']:.2f} [{lo:.2f}, {hi:.2f}]{gap}")
        lines.append(
            f"{c['case']:<14} {c['num_envs']:>5}  seeds {seeds[0]}-{seeds[-1]}: " + ", ".join(parts)
        )
    return lines


def format_heldout(metrics: dict[str, Any]) -> list[str]:
    """Lines of the held-out table (cells with a ``heldout`` block, docs/scale.md#held-out-instances):
    per cell and method the nominal mean return beside the held-out one (+- 95% CI, gap closed
    against the held-out references in brackets), then the held-out random and oracle returns."""
    cells = [c for c in metrics["cells"] if c.get("heldout")]
    if not cells:
        return []
    held = metrics["heldout"]
    methods = report_methods(metrics)
    lines = [
        f"Held-out instances (the family's sealed '{held['test']}' test, {held['episodes']} "
        "episodes per method, the same for every method): nominal mean return | held-out mean "
        "return +- 95% CI (gap closed)",
        f"{'case':<14} {'N':>5} "
        + " ".join(f"{m:>30}" for m in methods)
        + f" {'random':>8} {'oracle':>8}",
    ]
    for c in cells:
        ref = held["references"][c["case"]]
        cols = []
        for m in methods:
            r, h = c["methods"].get(m), c["heldout"]["methods"].get(m)
            if h is None:
                cols.append(f"{'n/a':>30}")
                continue
            gap = h.get("gap_closed")
            txt = f"{h['mean_return']:.2f}+-{_ci(h['ci95'])}" + (
                f" ({gap:.2f})" if gap is not None else ""
            )
            nominal = "n/a" if r is None else f"{r['mean_return']:.2f}"
            cols.append(f"{nominal + ' | ' + txt:>30}")
        orc = ref["oracle_averaging"]
        lines.append(
            f"{c['case']:<14} {c['num_envs']:>5} "
            + " ".join(cols)
            + f" {ref['random']['mean_return']:8.2f} "
            + (f"{orc['mean_return']:8.2f}" if orc else f"{'n/a':>8}")
        )
    return lines


def format_heads(metrics: dict[str, Any]) -> list[str]:
    """Lines of the every-head report (windy cells; families/windy/head_report.py)."""
    cells = [c for c in metrics["cells"] if c.get("heads")]
    if not cells:
        return []
    lines = [
        "Every head against its exact optimum (relative gap of its own objective, * within 2%; "
        "mu_bar: share of start cells choosing an exact best option; interruption condition: "
        "agreement with the exact one)"
    ]
    for c in cells:
        h = c["heads"]
        parts = [f"averaging {_gap(h['averaging'])}"]
        parts += [f"{name} {_gap(r)}" for name, r in (h.get("options") or {}).items()]
        if "mu_bar" in h:
            parts.append(f"mu_bar {h['mu_bar']['start_agreement']:.2f}")
        if "interruption_condition" in h:
            parts.append(f"interruption condition {h['interruption_condition']['agreement']:.3f}")
        if "interruption_controller" in h:
            ic = h["interruption_controller"]
            parts.append(
                f"exact returns: interruption {ic['expected_return']:.2f} "
                f"({ic['interruptions_per_episode']:.2f} interruptions/episode), oracle's "
                f"{ic['oracle_interruption_return']:.2f} ({ic['oracle_interruptions_per_episode']:.2f}) "
                f"vs oracle's options {ic['oracle_options_return']:.2f}"
            )
        lines.append(f"{c['case']:<14} {c['num_envs']:>5}  " + ", ".join(parts))
    return lines


def _gap(r: dict[str, Any]) -> str:
    return f"{r['rel_gap']:.3f}" + ("*" if r["within_2pct"] else "")


def _ci(x: float | None) -> str:
    return "nan" if x is None or not np.isfinite(x) else f"{x:.2f}"


def is_results_folder(out_dir: str | os.PathLike) -> bool:
    """Whether ``out_dir`` holds a ``metrics.json`` written by :func:`scale`."""
    try:
        return (
            json.loads((Path(out_dir) / METRICS_NAME).read_text()).get("experiment") == EXPERIMENT
        )
    except (OSError, ValueError, AttributeError):
        return False


COLOURS = {
    "averaging": "tab:green",
    "options": "tab:orange",
    "interruption": "tab:red",
    "hierarchy": "tab:blue",
    "random": "0.5",
    "oracle_averaging": "black",
}
FAMILY_STYLE = {"windy": dict(ls="-", marker="o"), "wargus": dict(ls="--", marker="s")}
UNITS = {"windy": "return (-steps)", "wargus": "items per episode"}
_OTHER_STYLES = (dict(ls=":", marker="^"), dict(ls="-.", marker="D"), dict(ls=":", marker="v"))


def family_style(fam: str) -> dict[str, Any]:
    """Line style of a family's curves (another family: one of a few more, by its name)."""
    if fam in FAMILY_STYLE:
        return FAMILY_STYLE[fam]
    return _OTHER_STYLES[sum(map(ord, fam)) % len(_OTHER_STYLES)]


def unit(fam: str) -> str:
    """The axis label of a family's returns."""
    return UNITS.get(fam, "return")


def plot_results(out_dir: str | os.PathLike) -> list[Path]:
    """(Re)draw ``scale.png`` from ``metrics.json``: training time, final return per method and
    frames/s against grid side and ``num_envs`` (means over seeds).
    """

    out = Path(out_dir)
    if not is_results_folder(out):
        raise ValueError(f"{str(out)!r} is not a scale results folder: {METRICS_NAME} is missing")
    metrics = json.loads((out / METRICS_NAME).read_text())
    cells, refs = metrics["cells"], metrics["references"]
    ns = sorted({c["num_envs"] for c in cells})
    families = list(dict.fromkeys(c["family"] for c in cells))  # in the order of the cases
    plt = pyplot()
    fig, axes = plt.subplots(
        2,
        1 + len(families),
        figsize=(5.2 * (1 + len(families)), 8.4),
        squeeze=False,
        layout="constrained",
    )
    cmap = plt.get_cmap("viridis")
    shade = {n: cmap(i / max(len(ns) - 1, 1) * 0.85) for i, n in enumerate(ns)}
    _plot_training_time(axes[0, 0], cells, families, ns, shade, metrics["total_frames"])
    _plot_throughput(axes[1, 0], cells, refs, ns)
    letters = "bcdefghijklmnopqrstuvwxyz"
    for j, fam in enumerate(families, start=1):
        top, bottom = letters[j - 1], letters[len(families) + j - 1]
        _plot_vs_grid_side(axes[0, j], cells, refs, metrics["methods"], fam, ns[-1], top, unit(fam))
        _plot_vs_num_envs(axes[1, j], cells, refs, metrics["methods"], fam, ns, bottom, unit(fam))
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        if ax.has_data():
            ax.legend(fontsize=7)
    seeds = metrics.get("seeds")
    fig.suptitle(
        "Scaled-up grids: training cost and final performance"
        + (f" (mean over {seeds} training seeds, 95% CI)" if seeds else ""),
        fontsize=11,
    )
    path = save_figure(fig, out / FIGURE)
    plt.close(fig)
    paths = [path]
    if any(len(c.get("curve") or []) > 1 for c in cells):
        paths.append(plot_curves(metrics, out / CURVES_FIGURE))
    return paths


def plot_curves(metrics: dict[str, Any], path: Path) -> Path:
    """``scale_curves.png``: per cell every method's test return against training frames and wall
    time (95% CI), with the references; a curve equal to an earlier one is dashed.
    """
    cells = [c for c in metrics["cells"] if len(c.get("curve") or []) > 1]
    plt = pyplot()
    fig, axes = plt.subplots(
        2, len(cells), figsize=(4.6 * len(cells), 7.2), squeeze=False, layout="constrained"
    )
    for j, c in enumerate(cells):
        ref = metrics["references"][c["case"]]
        label = unit(c["family"])
        for i, (x_key, x_label) in enumerate(
            (("frames", "training frames"), ("seconds", "training s"))
        ):
            ax = axes[i, j]
            xs = [p[x_key] for p in c["curve"]]
            drawn: list[list[float]] = []
            for m in metrics["methods"]:
                pts = [p["methods"].get(m) or {} for p in c["curve"]]
                ys = [np.nan if q.get("mean_return") is None else q["mean_return"] for q in pts]
                if all(np.isnan(ys)):
                    continue
                ci = np.array([q.get("ci95") or 0.0 for q in pts], dtype=float)
                same = any(np.allclose(ys, d, equal_nan=True) for d in drawn)  # e.g. options
                ax.plot(
                    xs, ys, color=COLOURS[m], marker=".", ls="--" if same else "-",
                    label=m + (" (= a line above)" if same else ""),
                )  # fmt: skip
                if not same:
                    ax.fill_between(
                        xs, np.array(ys) - ci, np.array(ys) + ci, color=COLOURS[m], alpha=0.12
                    )
                drawn.append(ys)
            for name in ("random", "oracle_averaging"):
                r = ref.get(name)
                if r is not None:
                    ax.axhline(
                        r["mean_return"], ls=":", color=COLOURS[name], label=name.replace("_", " ")
                    )
            ax.set(xlabel=x_label, ylabel=label, title=f"{c['case']} N={c['num_envs']}")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.suptitle("Scaled-up grids: learning curves (test return of each method)", fontsize=11)
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def _plot_training_time(
    ax, cells: list[dict], families: list[str], ns: list[int], shade: dict, total_frames: int
) -> None:
    """Panel (a): training time vs grid side, one line per family and num_envs."""
    for fam in families:
        for n in ns:
            sel = sorted(
                (c for c in cells if c["family"] == fam and c["num_envs"] == n),
                key=lambda c: c["grid_side"],
            )
            if sel:
                ax.plot(
                    [c["grid_side"] for c in sel],
                    [c["train_seconds"] for c in sel],
                    color=shade[n],
                    label=f"{fam} N={n}",
                    **family_style(fam),
                )
    ax.set(
        xlabel="grid side",
        ylabel="training time (s)",
        yscale="log",
        title=f"(a) training time, {total_frames} frames per cell",
    )


def _plot_throughput(ax, cells: list[dict], refs: dict[str, Any], ns: list[int]) -> None:
    """Panel (d): training frames/s vs num_envs, one line per case."""
    for case in refs:
        sel = sorted((c for c in cells if c["case"] == case), key=lambda c: c["num_envs"])
        if sel:
            ax.plot(
                [c["num_envs"] for c in sel],
                [c["frames_per_second"] or np.nan for c in sel],
                label=case,
                **family_style(sel[0]["family"]),
            )
    ax.set(
        xlabel="parallel environments N",
        ylabel="training frames/s",
        xscale="log",
        yscale="log",
        title="(d) training throughput (collection + learning)",
    )
    _num_envs_ticks(ax, ns)


def final_return(cell: dict[str, Any], method: str) -> tuple[float, tuple[float, float]] | None:
    """A cell's final return of ``method`` and its 95% CI as (below, above) error bars: over the
    training seeds where the cell has several (``over_seeds``: their mean, bootstrap CI), else the
    cell's run (CI over the test episodes); ``None`` where the method does not apply."""
    agg = (cell.get("over_seeds") or {}).get(method)
    if agg is not None:
        lo, hi = agg["mean_ci95"]
        return agg["mean_return"], (agg["mean_return"] - lo, hi - agg["mean_return"])
    r = cell["methods"].get(method)
    if r is None:
        return None
    err = r["ci95"] or 0.0
    return r["mean_return"], (err, err)


def _plot_vs_grid_side(
    ax,
    cells: list[dict],
    refs: dict[str, Any],
    methods: list[str],
    fam: str,
    n_max: int,
    letter: str,
    unit: str,
) -> None:
    """Panel (b) or (c): one family's final return per method vs grid side at ``n_max`` envs
    (95% CI bars; cells with several seeds: the mean over them, :func:`final_return`), the random
    and oracle references dotted."""
    sel = sorted(
        (c for c in cells if c["family"] == fam and c["num_envs"] == n_max),
        key=lambda c: c["grid_side"],
    )
    x = [c["grid_side"] for c in sel]
    for m in methods:
        pts = [(xx, final_return(c, m)) for xx, c in zip(x, sel)]
        pts = [(xx, r) for xx, r in pts if r is not None]
        if pts:
            ax.errorbar(
                [p[0] for p in pts],
                [p[1][0] for p in pts],
                yerr=np.array([p[1][1] for p in pts], dtype=float).T,
                color=COLOURS[m],
                marker="o",
                capsize=3,
                label=m,
            )
    for ref in ("random", "oracle_averaging"):
        ys = [(refs[c["case"]].get(ref) or {}).get("mean_return") for c in sel]
        if any(y is not None for y in ys):
            ax.plot(
                x,
                [np.nan if y is None else y for y in ys],
                ls=":",
                color=COLOURS[ref],
                marker="x",
                label=ref.replace("_", " "),
            )
    ax.set(
        xlabel="grid side",
        ylabel=unit,
        title=f"({letter}) {fam}: final performance, N={n_max}",
    )


def _plot_vs_num_envs(
    ax,
    cells: list[dict],
    refs: dict[str, Any],
    methods: list[str],
    fam: str,
    ns: list[int],
    letter: str,
    unit: str,
) -> None:
    """Panel (e) or (f): one family's final return vs num_envs, per case (line style) and method
    (colour)."""
    styles = ["-", "--", ":", "-."]
    for k, case in enumerate(
        c for c in refs if any(x["case"] == c and x["family"] == fam for x in cells)
    ):
        sel = sorted((c for c in cells if c["case"] == case), key=lambda c: c["num_envs"])
        for m in methods:
            pts = [(c["num_envs"], final_return(c, m)) for c in sel]
            pts = [(n, r) for n, r in pts if r is not None]
            if pts:
                ax.plot(
                    [p[0] for p in pts],
                    [p[1][0] for p in pts],
                    marker=".",
                    ls=styles[k % len(styles)],
                    color=COLOURS[m],
                    label=f"{case}: {m}",
                )
    ax.set(
        xlabel="parallel environments N",
        ylabel=unit,
        xscale="log",
        title=f"({letter}) {fam}: final performance vs N",
    )
    _num_envs_ticks(ax, ns)


def _num_envs_ticks(ax, ns: list[int]) -> None:
    """Tick the log-scaled num_envs axis at the values run, as plain integers."""
    ax.set_xticks(ns, [str(n) for n in ns])
    ax.minorticks_off()


__all__ = [
    "COLOURS",
    "CSV_FIELDS",
    "CSV_NAME",
    "CURVES_FIGURE",
    "EXPERIMENT",
    "FAMILY_STYLE",
    "FIGURE",
    "METRICS_NAME",
    "SEED_FIELD",
    "csv_fields",
    "csv_rows",
    "final_return",
    "format_heads",
    "format_heldout",
    "format_seeds",
    "format_table",
    "is_results_folder",
    "plot_curves",
    "plot_results",
    "report_methods",
]
