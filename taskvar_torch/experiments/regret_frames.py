"""Regret against training frames: each memoryless method's exact regret on every heads snapshot of
a run (``train.heads_every``), on the same paired episodes
(docs/memory.md#regret-against-training-frames; paper §3.3.1). Writes ``regret_by_frames.csv`` and
``regret_by_frames.png``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import METHODS
from taskvar_torch.contract import FAMILIES, family
from taskvar_torch.experiments.baselines import available_baselines
from taskvar_torch.experiments.paired import (
    affordable,
    episode_seed,
    exact_regret,
    parse_methods,
    play,
)
from taskvar_torch.experiments.plots import pyplot, save_figure
from taskvar_torch.experiments.results import write_csv
from taskvar_torch.experiments.shift import EvalPoint, Shift, parse_shift, shift_points
from taskvar_torch.factory import (
    calibrate,
    load_heads,
    make_env,
    make_method_controller,
    make_subtasks,
    training_states,
)
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.subtasks.base import Subtasks
from taskvar_torch.training.run_state import HEADS_SNAPSHOTS

CSV_NAME = "regret_by_frames.csv"
PNG_NAME = "regret_by_frames.png"
CSV_FIELDS = ("frames", "updates", "method", "regret_mean", "ci95", "exact_mean_return")


def run_paths(checkpoint: str | os.PathLike) -> tuple[Path, list[Path]]:
    """The final bundle and the heads snapshots (in frame order) of a run folder or its
    ``final.pt``; a one-line error where the run saved none."""
    path = Path(checkpoint)
    final = path / "final.pt" if path.is_dir() else path
    if not final.is_file():
        raise ValueError(f"no bundle at {str(final)!r}: give a run folder or its final.pt")
    snapshots = sorted((final.parent / HEADS_SNAPSHOTS).glob("heads_*.pt"))
    if not snapshots:
        raise ValueError(
            f"--by-frames: {str(final.parent)!r} has no heads snapshots "
            f"({HEADS_SNAPSHOTS}/heads_<frames>.pt); train with train.heads_every=N"
        )
    return final, snapshots


def oracle_families() -> list[str]:
    """The families that bring an exact oracle (``Family.oracle``)."""
    return sorted(n for n, f in FAMILIES.loaded().items() if f.exact_oracle)


def check_by_frames(checkpoint: str | os.PathLike, points: Sequence[EvalPoint]) -> Any:
    """Every one-line refusal before an episode is played: no snapshots, a shift curve, a family
    or env without an exact oracle. Returns the test point's oracle."""
    final, _ = run_paths(checkpoint)
    if len(points) != 1:
        raise ValueError("--by-frames takes one test point; drop the swept --shift values")
    cfg = points[0].cfg
    fam = family(cfg)
    oracle = None if fam.oracle is None else fam.oracle(cfg)
    if oracle is None or not hasattr(oracle, "optimal_return"):
        where = f"family {cfg.family!r}" if fam.oracle is None else f"this {cfg.family} env"
        raise ValueError(
            f"--by-frames needs the exact per-instance optimum, which {where} has no oracle for; "
            f"families with one: {', '.join(oracle_families())} (windy: small one-hot layouts)"
        )
    return oracle


def _memoryless(
    spec: str, subtasks: Subtasks, heads: Heads, checkpoint: str | os.PathLike
) -> list[str]:
    """The paper's methods among ``spec`` (``all``: those ``--method all`` plays); the recurrent
    and informed baselines are not memoryless (no exact value) and save no snapshots."""
    methods = parse_methods(spec, subtasks, heads, available_baselines(checkpoint), checkpoint)
    kept = [m for m in methods if m in METHODS]
    if not kept:
        raise ValueError(
            f"--by-frames plays the memoryless methods {list(METHODS)}; --method {spec} names none"
        )
    return kept


def regret_by_frames(
    checkpoint: str | os.PathLike,
    method: str = "all",
    test: str | None = None,
    shifts: Sequence[str | Shift] = (),
    episodes: int = 1000,
    seed: int | None = None,
    noise_seed: int | None = None,
    batch_size: int | None = None,
    exact: bool | None = None,
    out_dir: str | os.PathLike | None = None,
    plots: bool = True,
    controller: Sequence[str] = (),
) -> dict[str, Any]:
    """Each memoryless method's mean exact regret (95% CI) on each heads snapshot and the final
    heads, all on the same paired test episodes (``test``, ``shifts``, ``seed``, ``controller`` and
    ``exact`` as ``taskvar eval``'s; ``exact=False`` is refused).

    Returns ``{"test", "seed", "episodes", "methods", "optimum_mean_return", "points": [{"frames",
    "updates", "bundle", "methods": {m: {"regret_mean", "regret_ci95", "exact_mean_return"}}}]}`` in
    frame order; writes the CSV and PNG into ``out_dir`` (held by the caller) when given.
    """
    if int(episodes) < 1:
        raise ValueError(f"--episodes must be >= 1, got {episodes}")
    if exact is False:
        raise ValueError("--by-frames computes exact returns; drop --no-exact")
    shifts = [s if isinstance(s, Shift) else parse_shift(s) for s in shifts]
    final, snapshots = run_paths(checkpoint)
    heads, cfg = load_heads(final, controller=controller)
    test_name = test if test is not None else next(iter(family(cfg).tests))
    points = shift_points(cfg, test_name, shifts)
    oracle = check_by_frames(final, points)
    point = points[0]
    seed = episode_seed(cfg, test_name, seed)
    train_subtasks = make_subtasks(cfg, make_env(cfg, 1))
    methods = _memoryless(method, train_subtasks, heads, final)
    subtasks = make_subtasks(point.cfg, make_env(point.cfg, 1, instances=point.instances))
    bs = int(batch_size or cfg.eval.batch_size)
    # the paired episodes' instances and starts: drawn by the seed, whichever controller plays
    probe = make_method_controller(point.cfg, "averaging", heads, subtasks)
    r = play(probe, point, int(episodes), seed, bs, noise_seed)
    instance = {k[len("instance_") :]: v for k, v in r.items() if k.startswith("instance_")}
    start = r["start"]
    if exact is None and not affordable(oracle, instance):
        raise ValueError(
            "--by-frames: too many distinct instances for the oracle's exact returns; pass "
            "--exact to compute them anyway (slowly), or fewer --episodes"
        )
    optimum = None
    out_points = []
    for path in [*snapshots, final]:
        h, c = (heads, cfg) if path == final else load_heads(path, controller=controller)
        counters = load_checkpoint(path).get("counters", {})
        calibration = None  # the hierarchy's thresholds: on the training distribution
        if "hierarchy" in methods and c.train.robustness_threshold == "calibrated":
            calibration = calibrate(c, h, train_subtasks, training_states(c, h))
        per_method = {}
        for m in methods:
            ctrl = make_method_controller(point.cfg, m, h, subtasks, calibration=calibration)
            exact_r, optimum, regret = exact_regret(
                oracle, ctrl, point.cfg, instance, start, optimum
            )
            per_method[m] = {
                **regret,
                "exact_mean_return": float(np.mean(exact_r, dtype=np.float64)),
            }
        out_points.append(
            {
                "frames": int(counters.get("frames", 0)),
                "updates": int(counters.get("updates", 0)),
                "bundle": str(path),
                "methods": per_method,
            }
        )
    data = {
        "test": test_name,
        "shifts": [f"{s.key}={','.join(s.values)}" for s in shifts],
        "seed": seed,
        "episodes": int(episodes),
        "methods": methods,
        "optimum_mean_return": float(np.mean(optimum, dtype=np.float64)),
        "points": out_points,
    }
    if out_dir is not None:
        write_by_frames(Path(out_dir), data, plots, f"{cfg.family}: test {test_name}")
    return data


def csv_rows(data: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One row per (snapshot, method): ``frames, updates, method, regret_mean, ci95,
    exact_mean_return``."""
    return [
        {
            "frames": p["frames"],
            "updates": p["updates"],
            "method": m,
            "regret_mean": r["regret_mean"],
            "ci95": r["regret_ci95"],
            "exact_mean_return": r["exact_mean_return"],
        }
        for p in data["points"]
        for m, r in p["methods"].items()
    ]


def write_by_frames(out: Path, data: dict[str, Any], plots: bool, title: str) -> None:
    """``regret_by_frames.csv`` and (``plots``) ``regret_by_frames.png`` into ``out``; their names
    go into ``data["files"]``."""
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / CSV_NAME, csv_rows(data), CSV_FIELDS)
    data["files"] = [CSV_NAME]
    if plots:
        plot_regret_by_frames(data, out / PNG_NAME, title)
        data["files"].append(PNG_NAME)


def plot_regret_by_frames(data: Mapping[str, Any], path: Path, title: str) -> Path:
    """Each method's mean exact regret against training frames with its 95% CI band (log y where
    every value is positive; a regret of 0 is the per-instance optimum)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    xs = np.array([p["frames"] for p in data["points"]], dtype=np.float64)
    lows = []
    for i, m in enumerate(data["methods"]):  # markers and dashes: equal lines stay visible
        y = np.array([p["methods"][m]["regret_mean"] for p in data["points"]])
        ci = np.array([p["methods"][m]["regret_ci95"] for p in data["points"]], dtype=float)
        ci = np.nan_to_num(ci)  # one episode: no interval
        style = {"marker": "osD^"[i % 4], "ls": ("-", "--", ":", "-.")[i % 4], "ms": 7 - i}
        (line,) = ax.plot(xs, y, label=m, **style)
        ax.fill_between(xs, y - ci, y + ci, alpha=0.2, color=line.get_color())
        lows.append(float(np.min(y - ci)))
        lows.append(float(np.min(y)))
    if lows and min(lows) > 0:
        ax.set_yscale("log")
    ax.set_xlabel("training frames (heads snapshots; the last: final heads)")
    ax.set_ylabel("regret vs exact per-instance optimum\n(exact, mean over episodes, 95% CI)")
    ax.set_title(
        f"{title}, {data['episodes']} paired episodes (optimum {data['optimum_mean_return']:.3f})",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


def format_by_frames(data: Mapping[str, Any]) -> str:
    """The regrets as a table: one row per snapshot, one column per method (mean +- 95% CI)."""
    methods = data["methods"]
    head = f"{'frames':>10} " + " ".join(f"{m:>20}" for m in methods)
    lines = [
        f"regret against the exact per-instance optimum by training frames (test {data['test']}, "
        f"{data['episodes']} paired episodes, seed {data['seed']}; optimum "
        f"{data['optimum_mean_return']:.3f}):",
        head,
    ]
    for p in data["points"]:
        cells = [
            f"{p['methods'][m]['regret_mean']:11.4f} +-{p['methods'][m]['regret_ci95']:6.4f}"
            for m in methods
        ]
        lines.append(f"{p['frames']:>10} " + " ".join(f"{c:>20}" for c in cells))
    return "\n".join(lines)


__all__ = [
    "CSV_NAME",
    "PNG_NAME",
    "check_by_frames",
    "csv_rows",
    "format_by_frames",
    "oracle_families",
    "plot_regret_by_frames",
    "regret_by_frames",
    "run_paths",
    "write_by_frames",
]
