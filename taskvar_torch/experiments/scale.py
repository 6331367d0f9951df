"""Scaled-up grids (docs/scale.md): training time and final performance of the four
methods against grid size and against the number of parallel environments.

The protocol, top to bottom (:func:`scale`), for each *case* (a family config: windy 5x5, 25x25,
51x51 with 4 exits; Wargus 32x32, 64x64 with 3 patrols) and each ``num_envs`` value (a *cell*):

1. train every head with the real trainer (``train.train``) on the case's config with
   ``env.num_envs = N`` and the same frame budget for every cell (``total_frames``); the
   exploration schedule is scaled to the budget (``init_random_fraction``,
   ``eps_decay_fraction``), ``frames_per_batch`` is rounded to a multiple of N and
   ``updates_per_batch`` scaled with it, so every cell makes the same number of updates per frame
   as its family config; wall-clock training time and frames/s are recorded (one torch thread);
2. evaluate each method -- averaging (paper §3.1), options (§3.2), interruption (Algorithm 1) and
   hierarchy (Algorithm 2; Wargus only: the windy family has no composition hierarchy, "n/a") --
   on ``eval_episodes`` fresh test instances (``instances=test``, test seed ``seed + 1000``): mean
   return with a 95% CI (Wargus: the return is the number of items collected);
3. references on the *same* test episodes (same env seed: same instances, starts; paired): the
   uniformly random policy, and for windy the exact mean-MDP averaging optimum (the oracle's
   ``averaging_policy``, paper §3.1; value iteration on the mean MDP, a few seconds at 51x51),
   rolled out like the methods. ``gap_closed = (R - R_random) / (R_oracle - R_random)``: 0 is
   random, 1 is the best averaging policy (interruption may exceed 1).

Writes ``config.yaml`` (this experiment's config), ``cells/<case>-n<N>/`` (the trainer's logs and
config; ``final.pt`` only with ``keep_checkpoints``), ``scale.csv`` (one row per cell and method),
``metrics.json``, ``scale.png``; prints a table. ``taskvar plot OUT`` redraws ``scale.png``.

Examples:
    >>> cfg = load_scale_config(default_config_path(), quick=True)  # doctest: +SKIP
    >>> metrics = scale(cfg, "results/scale-quick")  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.modules import RandomPolicy
from tqdm.auto import tqdm

from taskvar_torch import keys
from taskvar_torch.config import (
    METHODS,
    Config,
    apply_overrides,
    config_to_dict,
    load_config,
    load_strict,
    save_config_yaml,
    windy_layout,
)
from taskvar_torch.experiments.evaluation import mean_ci95, run_episodes
from taskvar_torch.experiments.plots import _pyplot, save_figure
from taskvar_torch.experiments.results import refuse_existing_results, write_csv, write_json
from taskvar_torch.factory import load_heads, make_env, make_method_controller, make_subtasks
from taskvar_torch.families import family
from taskvar_torch.oracle import WindyOracle
from taskvar_torch.train import train

EXPERIMENT = "scale"
TEST_SEED_OFFSET = 1000
"""Test episodes use env seed ``seed + TEST_SEED_OFFSET`` (never a training seed)."""
CSV_NAME, METRICS_NAME, FIGURE = "scale.csv", "metrics.json", "scale.png"
CSV_FIELDS = (
    "case", "family", "grid_side", "cells", "num_envs", "frames", "updates", "frames_per_batch",
    "updates_per_batch", "train_seconds", "frames_per_second", "method", "mean_return", "ci95",
    "gap_closed", "random_return", "oracle_return", "interruptions_per_episode",
)  # fmt: skip


# --------------------------------------------------------------------------------------------
# config (mirrored by configs/scale.yaml, loaded strictly by taskvar_torch.config.load_strict)


@dataclass(frozen=True)
class ScaleCase:
    """One scaled family: a label, a family config and overrides applied to it."""

    name: str = ""
    """Label of the case in the table and plots (e.g. windy-25x25); unique."""
    config: str = ""
    """Family YAML (configs/*.yaml); a relative path is read beside the scale config."""
    overrides: tuple[str, ...] = ()
    """key.sub=value overrides of the family config for this case."""


@dataclass(frozen=True)
class ScaleConfig:
    """The scaled-up grids experiment: which cases, num_envs values, budgets."""

    override_example: ClassVar[str] = "total_frames=20000"
    """An override shown in the error for a malformed one (a class constant, not a config key)."""
    seed: int = 0
    """Seed of every cell's training (cfg.seed); test episodes use seed + 1000."""
    total_frames: int = 100_000
    """Training frames per cell (the same budget for every case and num_envs)."""
    init_random_fraction: float = 0.1
    """train.init_random_frames = this x total_frames."""
    eps_decay_fraction: float = 0.5
    """train.eps_decay_frames = this x total_frames."""
    updates_per_frame: float | None = None
    """Gradient updates per training frame in every cell (train.updates_per_batch =
    round(this x frames_per_batch)); null keeps each family config's own ratio."""
    num_envs: tuple[int, ...] = (16, 64, 256)
    """Parallel training environments (env.num_envs) of each cell."""
    eval_episodes: int = 500
    """Test episodes per method, per cell (fresh test instances)."""
    eval_batch_size: int = 500
    """Test environments run in parallel."""
    cases: list[ScaleCase] = field(default_factory=list)
    """The scaled families, smallest grid first within a family."""
    only: tuple[str, ...] = ()
    """Names of the cases to run; empty: all."""
    overrides: tuple[str, ...] = ()
    """key.sub=value overrides applied to every case's family config (before the case's own)."""
    keep_checkpoints: bool = False
    """Keep each cell's cells/<case>-n<N>/final.pt (with its replay buffer: large)."""
    quick_overrides: tuple[str, ...] = ()
    """Overrides of this config applied by --quick."""

    def __post_init__(self):
        if self.total_frames < 1:
            raise ValueError(f"total_frames must be >= 1, got {self.total_frames}")
        for name in ("init_random_fraction", "eps_decay_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.updates_per_frame is not None and not 0 < self.updates_per_frame <= 64:
            raise ValueError(
                f"updates_per_frame must be in (0, 64] or null, got {self.updates_per_frame}"
            )
        if not self.num_envs or min(self.num_envs) < 1:
            raise ValueError(
                f"num_envs must be a non-empty list of ints >= 1, got {list(self.num_envs)}"
            )
        for name in ("eval_episodes", "eval_batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.cases:
            raise ValueError("cases must list at least one {name, config} case")
        names = [c.name for c in self.cases]
        for i, c in enumerate(self.cases):
            if not c.name or not c.config:
                raise ValueError(f"cases[{i}] needs a name and a config, got {c}")
        if len(set(names)) != len(names):
            raise ValueError(f"case names must be unique, got {names}")
        unknown = [n for n in self.only if n not in names]
        if unknown:
            raise ValueError(f"only must name cases among {names}, got {unknown}")

    def selected(self) -> tuple[ScaleCase, ...]:
        """The cases to run (``only``, or all)."""
        return tuple(c for c in self.cases if not self.only or c.name in self.only)


def default_config_path() -> Path:
    """``configs/scale.yaml`` of the repository (or of the working directory)."""
    here = Path(__file__).resolve().parents[2] / "configs" / "scale.yaml"
    return here if here.is_file() else Path("configs") / "scale.yaml"


def load_scale_config(
    path: str | os.PathLike, overrides: Sequence[str] = (), quick: bool = False
) -> ScaleConfig:
    """Load ``configs/scale.yaml`` strictly (unknown keys and bad types are one-line errors), apply
    ``quick_overrides`` with ``quick``, then ``key=value`` overrides; case config paths are resolved
    beside the YAML file, and every case's family config is loaded (strictly) to fail early.

    Loading is :func:`taskvar_torch.config.load_strict`, the training configs' loader; the quick
    overrides are read (and checked) only with ``quick``.
    """
    path = Path(path)
    cfg = load_strict(
        ScaleConfig,
        path,
        overrides,
        quick=quick,
        quick_overrides=lambda c: c.quick_overrides,
        check_quick=False,
    )
    cases = []
    for c in cfg.cases:
        p = Path(c.config)
        if not p.is_absolute():
            p = path.parent / p
        cases.append(dataclasses.replace(c, config=str(p)))
    cfg = dataclasses.replace(cfg, cases=cases)
    for c in cfg.selected():
        case_config(cfg, c, cfg.num_envs[0])  # a typo in a case fails now, not after an hour
    return cfg


def scale_config_to_dict(cfg: ScaleConfig) -> dict[str, Any]:
    """Plain nested data of ``cfg`` (tuples as lists)."""
    return config_to_dict(cfg)


def case_config(cfg: ScaleConfig, case: ScaleCase, num_envs: int) -> Config:
    """The family config of one cell: the case's YAML, the budget, ``num_envs`` and the overrides.

    ``frames_per_batch`` becomes a multiple of ``num_envs`` (at least one step of every env) and
    ``updates_per_batch`` is scaled with it, keeping the config's updates per frame (or
    ``cfg.updates_per_frame`` when set).
    """
    base = load_config(case.config, [*cfg.overrides, *case.overrides])
    t = base.train
    n = int(num_envs)
    fpb = max(n, round(t.frames_per_batch / n) * n)
    fpb = min(
        fpb, max(n, (cfg.total_frames // n) * n)
    )  # at least two batches when the budget allows
    ratio = (
        t.updates_per_batch / t.frames_per_batch
        if cfg.updates_per_frame is None
        else cfg.updates_per_frame
    )
    upb = max(1, round(ratio * fpb)) if ratio > 0 else 0
    return apply_overrides(
        base,
        [
            f"seed={cfg.seed}",
            f"env.num_envs={n}",
            f"train.total_frames={cfg.total_frames}",
            f"train.init_random_frames={int(cfg.init_random_fraction * cfg.total_frames)}",
            f"train.eps_decay_frames={int(cfg.eps_decay_fraction * cfg.total_frames)}",
            f"train.frames_per_batch={fpb}",
            f"train.updates_per_batch={upb}",
            f"train.buffer_size={max(min(t.buffer_size, cfg.total_frames), t.batch_size)}",
            "train.checkpoint_every=0",
            f"train.log_every={max(cfg.total_frames // 10, 1)}",
        ],
    )


# --------------------------------------------------------------------------------------------
# evaluation on fresh test instances


def grid_side(cfg: Config) -> int:
    """The grid's side length (windy: max of height and width; Wargus: ``size``)."""
    return family(cfg).grid_side(cfg)


def make_test_env(cfg: Config, num_envs: int, seed: int, index_offset: int = 0) -> EnvBase:
    """The family env on fresh test instances; the same ``seed`` gives the same episodes."""
    return make_env(
        cfg,
        num_envs,
        seed=seed,
        index_offset=index_offset,
        instances="test",
        validate_actions=False,
    )


class TablePolicy(nn.Module):
    """``action = table[cell]``: a tabular deterministic policy (the oracle's averaging optimum)."""

    def __init__(self, table: torch.Tensor):
        super().__init__()
        self.register_buffer("table", table.to(torch.int64))

    def forward(self, cell: torch.Tensor) -> torch.Tensor:
        return self.table[cell]


def make_policy(name: str, cfg: Config, heads: Any = None, subtasks: Any = None, env: Any = None):
    """A TorchRL policy: a method's controller on ``heads``, ``random`` or ``oracle_averaging``."""

    if name == "random":
        return RandomPolicy(env.action_spec)
    if name == "oracle_averaging":
        oracle = WindyOracle(
            windy_layout(cfg.env),
            gamma=cfg.train.gamma,
            horizon=cfg.env.horizon,
            train_instances=cfg.env.instances,
            device=cfg.device,
        )
        return TensorDictModule(TablePolicy(oracle.averaging_policy()), [keys.CELL], [keys.ACTION])
    return make_method_controller(cfg, name, heads, subtasks)


def evaluate(
    cfg: Config, policy_name: str, episodes: int, batch_size: int, heads: Any = None
) -> dict[str, float] | None:
    """Mean return (95% CI), length and interruptions of ``policy_name`` over ``episodes`` test
    episodes (global indices ``0..episodes-1`` at the test seed: the same for every policy).

    ``None`` where the method does not apply (hierarchy without a composition hierarchy)."""

    seed = cfg.seed + TEST_SEED_OFFSET
    probe = make_test_env(cfg, 1, seed)
    subtasks = make_subtasks(cfg, probe)
    if policy_name == "hierarchy" and subtasks.hierarchy is None:
        return None
    torch.manual_seed(seed)  # the random policy's action stream
    policy = make_policy(policy_name, cfg, heads, subtasks, probe)
    returns, lengths, inter = [], [], []
    for lo in range(0, int(episodes), int(batch_size)):
        n = min(int(batch_size), int(episodes) - lo)
        env = make_test_env(cfg, n, seed, lo)
        if hasattr(policy, "primer"):
            env = TransformedEnv(env, policy.primer())
        if policy_name == "random":
            policy = RandomPolicy(env.action_spec)
        out = run_episodes(env, policy)
        returns.append(out["return"].double().cpu())
        lengths.append(out["length"].double().cpu())
        inter.append(out["interruptions"].double().cpu())
    r = torch.cat(returns)
    mean, ci = mean_ci95(r)
    result = {
        "mean_return": mean,
        "ci95": ci,
        "mean_length": float(torch.cat(lengths).mean()),
        "episodes": int(r.numel()),
    }
    if policy_name in ("options", "interruption", "hierarchy"):
        result["interruptions_per_episode"] = float(torch.cat(inter).mean())
    return result


def references(cfg: Config, episodes: int, batch_size: int) -> dict[str, Any]:
    """The random policy and (windy) the oracle's averaging optimum on the same test episodes."""
    t0 = time.perf_counter()
    refs: dict[str, Any] = {"random": evaluate(cfg, "random", episodes, batch_size)}
    if family(cfg).exact_oracle:
        refs["oracle_averaging"] = evaluate(cfg, "oracle_averaging", episodes, batch_size)
        refs["oracle_note"] = (
            "mean-MDP optimal averaging policy (exact value iteration, paper "
            "§3.1), rolled out on the same test episodes"
        )
    else:
        refs["oracle_averaging"] = None
        refs["oracle_note"] = "no exact oracle for Wargus"
    refs["seconds"] = time.perf_counter() - t0
    return refs


def gap_closed(ret: float, random_ret: float, oracle_ret: float | None) -> float | None:
    """``(ret - random) / (oracle - random)``; ``None`` without an oracle or a gap."""
    if oracle_ret is None or abs(oracle_ret - random_ret) < 1e-9:
        return None
    return (ret - random_ret) / (oracle_ret - random_ret)


# --------------------------------------------------------------------------------------------
# the experiment


def run_cell(
    cfg: ScaleConfig,
    case: ScaleCase,
    num_envs: int,
    out: Path,
    refs: dict[str, Any],
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train one (case, num_envs) cell with the real trainer, time it, evaluate every method."""

    ccfg = case_config(cfg, case, num_envs)
    cell_dir = out / "cells" / f"{case.name}-n{num_envs}"
    result = train(ccfg, cell_dir, progress=False, overwrite=overwrite)
    heads, _ = load_heads(result["final"], device=ccfg.device)
    if not cfg.keep_checkpoints:
        Path(result["final"]).unlink(missing_ok=True)
    t0 = time.perf_counter()
    methods = {m: evaluate(ccfg, m, cfg.eval_episodes, cfg.eval_batch_size, heads) for m in METHODS}
    rand = refs["random"]["mean_return"]
    orc = refs["oracle_averaging"]["mean_return"] if refs["oracle_averaging"] else None
    for r in methods.values():
        if r is not None:
            r["gap_closed"] = gap_closed(r["mean_return"], rand, orc)
    secs = float(result["seconds"])
    return {
        "case": case.name,
        "family": ccfg.family,
        "grid_side": grid_side(ccfg),
        "cells": family(ccfg).cells(ccfg),
        "num_envs": int(num_envs),
        "frames": int(result["frames"]),
        "updates": int(result["updates"]),
        "frames_per_batch": ccfg.train.frames_per_batch,
        "updates_per_batch": ccfg.train.updates_per_batch,
        "hidden": list(ccfg.heads.hidden),
        "obs_encoding": family(ccfg).observation(ccfg),
        "train_seconds": secs,
        "frames_per_second": result["frames"] / secs if secs > 0 else None,
        "eval_seconds": time.perf_counter() - t0,
        "methods": methods,
    }


def scale(
    cfg: ScaleConfig,
    out_dir: str | os.PathLike,
    progress: bool = True,
    quick: bool = False,
    plots: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run every (case, num_envs) cell, write the results folder, print the table.

    ``overwrite``: replace the results (and cell runs) already in ``out_dir``; without it such a
    folder is refused.

    Returns:
        The metrics dict written to ``metrics.json``.
    """
    out = Path(out_dir)
    refuse_existing_results(out, overwrite, "taskvar experiment scale")
    out.mkdir(parents=True, exist_ok=True)
    save_config_yaml(cfg, out / "config.yaml")
    t0 = time.perf_counter()
    cases = cfg.selected()
    refs: dict[str, Any] = {}
    cells: list[dict[str, Any]] = []
    bar = tqdm(
        total=len(cases) * len(cfg.num_envs), disable=not progress, desc="scale", unit="cell"
    )
    for case in cases:
        refs[case.name] = references(
            case_config(cfg, case, cfg.num_envs[0]), cfg.eval_episodes, cfg.eval_batch_size
        )
        for n in cfg.num_envs:
            bar.set_postfix_str(f"{case.name} N={n}")
            cells.append(run_cell(cfg, case, n, out, refs[case.name], overwrite))
            bar.update(1)
    bar.close()
    metrics = {
        "experiment": EXPERIMENT,
        "quick": bool(quick),
        "methods": list(METHODS),
        "total_frames": cfg.total_frames,
        "num_envs": list(cfg.num_envs),
        "eval_episodes": cfg.eval_episodes,
        "test_seed": cfg.seed + TEST_SEED_OFFSET,
        "threads": torch.get_num_threads(),
        "references": refs,
        "cells": cells,
        "wall_seconds": time.perf_counter() - t0,
        "notes": {
            "return": "undiscounted test return (windy: -steps to the goal; Wargus: items collected)",
            "ci95": "half-width of a normal-approximation 95% confidence interval of the mean",
            "gap_closed": "(R - R_random) / (R_oracle_averaging - R_random) on the same episodes",
            "hierarchy": "n/a for windy (no composition hierarchy in the family)",
        },
    }
    write_csv(out / CSV_NAME, csv_rows(metrics), CSV_FIELDS)
    write_json(out / METRICS_NAME, metrics)
    if plots:  # else ``taskvar plot DIR`` draws it from the folder
        plot_results(out)
    print(format_table(metrics))
    print(f"wrote {out / METRICS_NAME}, {out / CSV_NAME}" + (f", {out / FIGURE}" if plots else ""))
    return metrics


def csv_rows(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per (cell, method), references in every row."""
    rows = []
    for c in metrics["cells"]:
        ref = metrics["references"][c["case"]]
        orc = ref["oracle_averaging"]
        for m in METHODS:
            r = c["methods"].get(m)
            row = {k: c[k] for k in CSV_FIELDS if k in c}
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
    """One line per cell: time, frames/s, each method's mean return (CI), the references."""
    lines = [
        f"Scaled-up grids: {metrics['total_frames']} training frames per cell, "
        f"{metrics['eval_episodes']} test episodes per method "
        "per cell: mean return +- 95% CI (windy: -steps, and in brackets the gap closed, "
        "(R - random) / (oracle - random); Wargus: items per episode)",
        f"{'case':<14} {'N':>5} {'updates':>7} {'train s':>8} {'frames/s':>9} "
        + " ".join(f"{m:>21}" for m in METHODS)
        + f" {'random':>8} {'oracle':>8}",
    ]
    for c in metrics["cells"]:
        ref = metrics["references"][c["case"]]
        cols = []
        for m in METHODS:
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
            f"{c['case']:<14} {c['num_envs']:>5} {c['updates']:>7} {c['train_seconds']:8.1f} "
            f"{c['frames_per_second'] or 0:9.0f} "
            + " ".join(cols)
            + f" {ref['random']['mean_return']:8.2f} "
            + (f"{orc['mean_return']:8.2f}" if orc else f"{'n/a':>8}")
        )
    lines.append(f"wall time {metrics['wall_seconds']:.0f} s, {metrics['threads']} torch thread(s)")
    return "\n".join(lines)


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


def plot_results(out_dir: str | os.PathLike) -> list[Path]:
    """(Re)draw ``scale.png`` from ``metrics.json``: (a) training time vs grid side per num_envs,
    (b, c) final return per method vs grid side (windy, Wargus; at the largest num_envs, references
    dashed), (d) frames/s vs num_envs per case, (e, f) final return per method vs num_envs."""

    out = Path(out_dir)
    if not is_results_folder(out):
        raise ValueError(f"{str(out)!r} is not a scale results folder: {METRICS_NAME} is missing")
    metrics = json.loads((out / METRICS_NAME).read_text())
    cells, refs = metrics["cells"], metrics["references"]
    ns = sorted({c["num_envs"] for c in cells})
    families = [f for f in ("windy", "wargus") if any(c["family"] == f for c in cells)]
    plt = _pyplot()
    fig, axes = plt.subplots(
        2,
        1 + len(families),
        figsize=(5.2 * (1 + len(families)), 8.4),
        squeeze=False,
        layout="constrained",
    )
    cmap = plt.get_cmap("viridis")
    shade = {n: cmap(i / max(len(ns) - 1, 1) * 0.85) for i, n in enumerate(ns)}

    ax = axes[0, 0]  # (a) training time vs grid side
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
                    **FAMILY_STYLE[fam],
                )
    ax.set(
        xlabel="grid side",
        ylabel="training time (s)",
        yscale="log",
        title=f"(a) training time, {metrics['total_frames']} frames per cell",
    )

    ax = axes[1, 0]  # (d) frames/s vs num_envs
    for case in refs:
        sel = sorted((c for c in cells if c["case"] == case), key=lambda c: c["num_envs"])
        if sel:
            ax.plot(
                [c["num_envs"] for c in sel],
                [c["frames_per_second"] or np.nan for c in sel],
                label=case,
                **FAMILY_STYLE[sel[0]["family"]],
            )
    ax.set(
        xlabel="parallel environments N",
        ylabel="training frames/s",
        xscale="log",
        yscale="log",
        title="(d) training throughput (collection + learning)",
    )
    _num_envs_ticks(ax, ns)

    n_max = ns[-1]
    for j, fam in enumerate(families, start=1):
        unit = "items per episode" if fam == "wargus" else "return (-steps)"
        ax = axes[0, j]  # (b/c) performance vs grid side at the largest N
        sel = sorted(
            (c for c in cells if c["family"] == fam and c["num_envs"] == n_max),
            key=lambda c: c["grid_side"],
        )
        x = [c["grid_side"] for c in sel]
        for m in metrics["methods"]:
            pts = [(xx, c["methods"].get(m)) for xx, c in zip(x, sel)]
            pts = [(xx, r) for xx, r in pts if r is not None]
            if pts:
                ax.errorbar(
                    [p[0] for p in pts],
                    [p[1]["mean_return"] for p in pts],
                    yerr=[p[1]["ci95"] or 0.0 for p in pts],
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
            title=f"({'bc'[j - 1]}) {fam}: final performance, N={n_max}",
        )

        ax = axes[1, j]  # (e/f) performance vs num_envs, per case (line style) and method (colour)
        styles = ["-", "--", ":", "-."]
        for k, case in enumerate(
            c for c in refs if any(x["case"] == c and x["family"] == fam for x in cells)
        ):
            sel = sorted((c for c in cells if c["case"] == case), key=lambda c: c["num_envs"])
            for m in metrics["methods"]:
                pts = [(c["num_envs"], c["methods"].get(m)) for c in sel]
                pts = [(n, r) for n, r in pts if r is not None]
                if pts:
                    ax.plot(
                        [p[0] for p in pts],
                        [p[1]["mean_return"] for p in pts],
                        marker=".",
                        ls=styles[k % len(styles)],
                        color=COLOURS[m],
                        label=f"{case}: {m}",
                    )
        ax.set(
            xlabel="parallel environments N",
            ylabel=unit,
            xscale="log",
            title=f"({'ef'[j - 1]}) {fam}: final performance vs N",
        )
        _num_envs_ticks(ax, ns)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        if ax.has_data():
            ax.legend(fontsize=7)
    fig.suptitle("Scaled-up grids: training cost and final performance", fontsize=11)
    path = save_figure(fig, out / FIGURE)
    plt.close(fig)
    return [path]


def _num_envs_ticks(ax, ns: list[int]) -> None:
    """Tick the log-scaled num_envs axis at the values run, as plain integers."""
    ax.set_xticks(ns, [str(n) for n in ns])
    ax.minorticks_off()


__all__ = [
    "METHODS",
    "ScaleCase",
    "ScaleConfig",
    "case_config",
    "default_config_path",
    "evaluate",
    "format_table",
    "is_results_folder",
    "load_scale_config",
    "plot_results",
    "references",
    "scale",
]
