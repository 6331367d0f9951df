"""The exact oracle's table of a windy layout per start cell, and a picture of the grid
(docs/oracle.md#the-oracle-table).

Usage: ``python -m taskvar_torch.families.windy.oracle_table [--layout default] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from taskvar_torch.experiments.plots import pyplot, save_figure
from taskvar_torch.families.windy import WindyOracle, render
from taskvar_torch.families.windy import dynamics as windy

_ARROW = {0: (0, -0.3), 1: (0, 0.3), 2: (0.3, 0), 3: (-0.3, 0)}  # (dx, dy) in image coordinates


def oracle_table(layout: str = "default") -> dict:
    """Per-start-cell exact figures of the averaging policy and the exit options."""
    oracle = WindyOracle(layout)
    pi = oracle.averaging_policy()
    train = oracle.expected_return(pi, "train", starts=None)  # (S,)
    south = oracle.expected_return(pi, "south", starts=None)
    mean_mdp = oracle.mean_mdp_return(pi, start=None)
    opts = {
        name: oracle.expected_return(oracle.option_policies()[o], "train", starts=None)
        for o, name in enumerate(oracle.option_names)
    }
    rows = []
    for cell in oracle.start_cells.tolist():
        row = {
            "start": list(divmod(cell, oracle.layout.width)),
            "averaging_train": float(train[cell]),
            "averaging_south": float(south[cell]),
            "averaging_mean_mdp": float(mean_mdp[cell]),
        }
        row.update({f"{n}_train": float(v[cell]) for n, v in opts.items()})
        rows.append(row)
    return {
        "layout": layout,
        "gamma": oracle.gamma,
        "horizon": oracle.horizon,
        "rows": rows,
        "averaging_train_uniform_start": float(oracle.expected_return(pi, "train")),
        "per_cell_train": train.tolist(),
        "policy": pi.tolist(),
    }


def format_table(result: dict) -> str:
    """The table as fixed-width text."""
    names = [k for k in result["rows"][0] if k.endswith("_train") and k != "averaging_train"]
    head = f"{'start':>8} {'avg (train)':>12} {'avg (south)':>12} {'avg (mean MDP)':>15}"
    head += "".join(f" {n:>18}" for n in names)
    lines = [
        f"Exact oracle, windy layout {result['layout']!r}: expected {result['horizon']}-step return "
        "(instance ~ training distribution, held fixed per episode)",
        head,
    ]
    for r in result["rows"]:
        line = (
            f"{str(tuple(r['start'])):>8} {r['averaging_train']:12.3f} {r['averaging_south']:12.3f}"
        )
        line += f" {r['averaging_mean_mdp']:15.3f}" + "".join(f" {r[n]:18.3f}" for n in names)
        lines.append(line)
    lines.append(
        f"uniform start: averaging policy {result['averaging_train_uniform_start']:.3f} "
        "(exact, Gauss-Legendre quadrature over p)"
    )
    return "\n".join(lines)


def plot_grid(layout: str, result: dict, path: Path) -> None:
    """PNG of the grid with the averaging policy's actions and expected returns per cell."""

    plt = pyplot()
    lay = (
        windy.WindyLayout.named(layout)
        if layout in windy.LAYOUTS
        else windy.WindyLayout.from_map(layout)
    )
    px = render.CELL_PX
    fig, ax = plt.subplots(figsize=(1.2 * lay.width + 1, 1.2 * lay.height + 1))
    ax.imshow(render.windy_rgb(lay, None, "north", cell_px=px))
    for cell, (a, v) in enumerate(zip(result["policy"], result["per_cell_train"])):
        ch = lay.char(cell)
        if ch in "#G":
            continue
        r, c = divmod(cell, lay.width)
        x, y = (c + 0.5) * px, (r + 0.5) * px
        dx, dy = _ARROW[a]
        ax.annotate(
            "", (x + dx * px, y + dy * px), (x, y), arrowprops=dict(arrowstyle="->", lw=1.5)
        )
        ax.text(x, y + 0.38 * px, f"{v:.1f}", ha="center", va="center", fontsize=7)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(
        f"windy '{layout}': averaging policy and exact expected return\n(wind arrows show a north gust)"
    )
    save_figure(fig, path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--layout", default="default", help=f"one of {sorted(windy.LAYOUTS)}")
    ap.add_argument("--out", default="results/oracle", help="results folder")
    args = ap.parse_args(argv)
    torch.set_num_threads(max(1, min(2, torch.get_num_threads())))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = oracle_table(args.layout)
    print(format_table(result))
    (out / "oracle_table.json").write_text(json.dumps(result, indent=2))
    plot_grid(args.layout, result, out / "grid.png")
    print(f"wrote {out / 'oracle_table.json'} and {out / 'grid.png'}")
    return result


if __name__ == "__main__":
    main()
