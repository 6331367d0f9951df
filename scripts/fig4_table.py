"""Side-by-side table of Wargus Figure 4 result folders (an ablation, or runs to compare).

For each folder (``taskvar experiment wargus-fig4 --out DIR``) and method: mean items per nominal
test episode over all trials and over trials 1-250 (+- std across repetitions, and a 95% CI
half-width), the final score, trials to 90% of the maximum (the paper's bars) and of the final
level, interruptions and ``item_lost`` events per test episode, and the hierarchy's control split.
Everything but the control split and the per-episode counts is recomputed from ``metrics.json``'s
per-repetition curves (so folders written before a metric existed still compare, and ``--reps`` /
``--trials`` cut a longer run to an ablation's size; the split and counts stay over the whole run).

Usage:
    python scripts/fig4_table.py NAME=DIR [NAME=DIR ...] [--markdown]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from taskvar_torch.config import METHODS
from taskvar_torch.experiments.curves import trials_to_fraction, trials_to_fraction_of_max
from taskvar_torch.families.wargus.fig4_metrics import mean_over_trials


def rows_of(
    name: str, folder: Path, max_reps: int | None = None, max_trials: int | None = None
) -> list[list[str]]:
    m = json.loads((folder / "metrics.json").read_text())
    ctrl = m["hierarchy_trace"]["all_trials"]["per_subtask"]
    split = "/".join(f"{100 * ctrl.get(o, 0):.0f}" for o in ("TG+FE", "TG", "FE"))
    out = []
    for method in METHODS:
        x = m["methods"][method]
        per_rep = np.asarray(x["curve_per_rep"], dtype=float)[:max_reps, :max_trials]  # (R, T)
        curve = per_rep.mean(0)
        final = curve[-max(1, int(np.ceil(0.1 * curve.size))) :].mean()
        a, f = mean_over_trials(per_rep), mean_over_trials(per_rep, 250)
        lost = x.get("item_lost_per_episode")
        out.append(
            [
                name,
                method,
                f"{a['mean']:.2f} +- {a['std']:.2f} ({a['ci95']:.2f})",
                f"{f['mean']:.2f} +- {f['std']:.2f}",
                f"{final:.2f}",
                str(trials_to_fraction_of_max(curve)),
                str(trials_to_fraction(curve)[0]),
                f"{x['interruptions_per_episode']:.1f}",
                "-" if lost is None else f"{lost:.1f}",
                split if method == "hierarchy" else "",
            ]
        )
    return out


HEADER = [
    "run",
    "method",
    "mean items, all trials (+-std, CI)",
    f"trials 1-{250}",
    "final",
    "90% of max",
    "90% of final",
    "control changes / ep",
    "item_lost / ep",
    "control root/TG/FE %",
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="NAME=DIR")
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table")
    ap.add_argument("--reps", type=int, default=None, help="use the first N repetitions only")
    ap.add_argument("--trials", type=int, default=None, help="use the first N trials only")
    args = ap.parse_args()
    rows = []
    for spec in args.runs:
        name, _, folder = spec.partition("=")
        rows += rows_of(name, Path(folder), args.reps, args.trials)
    if args.markdown:
        print("| " + " | ".join(HEADER) + " |")
        print("|" + "---|" * len(HEADER))
        for r in rows:
            print("| " + " | ".join(r) + " |")
        return
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(HEADER)]
    for r in [HEADER, *rows]:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))


if __name__ == "__main__":
    main()
