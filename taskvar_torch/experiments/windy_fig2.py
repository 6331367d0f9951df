"""Windy Figure 2 with the learnt networks (paper §3.3.1; docs/windy-fig2.md).

The protocol, top to bottom (:func:`windy_fig2`):

1. train every head (``train.train`` into ``OUT/train``) or load a given checkpoint;
2. build the averaging, options and interruption controllers (Algorithm 1) on the learnt heads;
3. for each test distribution (``train``: the training distribution; ``south_only``: every wind
   pushes south) and each of R runs (seed ``cfg.seed + 1 + run``), play E test episodes with
   every method on *paired* rollouts: envs with the same seed give each method the same instance,
   start cell and gust stream per episode (common random numbers, ``rng.py``);
4. the *null* curve: averaging against itself with an independent gust stream (``noise_seed=1``,
   same instances and starts) -- what "no worse" looks like for two equally good policies;
5. the *exact* figure (layouts small enough for the oracle): per episode, the exact expected
   return of each learnt controller in that episode's (instance, start), from the Markov chain on
   (cell, running option) built from the trained heads' tables (``WindyOracle.controller_return``);
6. where interruption fired (cells, running option), and Theorem 1's premise at each firing:
   ``V^{mu_bar}(s') <= V^{m, mu_bar}(s')`` with the learnt ``V^{mu_bar}`` and the exact discounted
   value of the learnt options controller in the test instance ``m``, with the outcome per case.

Writes ``config.yaml``, ``train/`` (checkpoints, logs), ``episodes.csv``, ``metrics.json``,
``fig2_train.png``, ``fig2_south_only.png``, ``interruptions_heatmap.png``; prints a table.

Examples:
    >>> cfg = load_config("configs/windy.yaml", quick=True)  # doctest: +SKIP
    >>> metrics = windy_fig2(cfg, "results/windy-fig2-quick")  # doctest: +SKIP
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torchrl.envs import TransformedEnv
from tqdm.auto import tqdm

from taskvar_torch import keys
from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import METHODS as ALL_METHODS
from taskvar_torch.config import (
    Config,
    load_config,
    save_config_yaml,
    windy_layout,
)
from taskvar_torch.controllers import Controller, make_controller
from taskvar_torch.envs import windy
from taskvar_torch.envs.instances import WindyInstances
from taskvar_torch.envs.windy_env import WindyGridEnv
from taskvar_torch.experiments.bundle_eval import eval_bundle
from taskvar_torch.experiments.evaluation import mean_ci95, paired_summary, run_episodes
from taskvar_torch.experiments.plots import plot_interruption_heatmap, plot_sorted_differences
from taskvar_torch.experiments.results import refuse_existing_results, write_csv, write_json
from taskvar_torch.families import EXACT_ORACLE_CELLS, FAMILIES
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.oracle import (  # the exact maths; also importable from this module
    WindyOracle,
    discounted_chain_values,  # noqa: F401
    exact_returns,
    firing_values,
    learnt_vs_oracle_by_start,
)
from taskvar_torch.train import (
    check_device,
    check_output_folder,
    load_heads,
    make_env,
    make_subtasks,
    run_files,
    train,
)

METHODS = tuple(m for m in ALL_METHODS if m != "hierarchy")
"""Methods of Figure 2, every method but hierarchy (the windy family has no composition
hierarchy): the flat baseline, options without interruption, Algorithm 1."""
DISTRIBUTIONS = {"train": "train", "south_only": "south"}
"""metrics.json key -> test instance distribution (``train``: the training distribution)."""
NULL_NOISE_SEED = 1
"""Gust-stream salt of the null comparison's second averaging rollout (same instances, starts)."""
EXACT_MAX_CELLS = EXACT_ORACLE_CELLS
"""The exact figure is computed on layouts with at most this many cells (the family registry's
exact-oracle limit)."""
EXACT_ATOL = 1e-9
"""Exact differences within this of 0 count as ties ("no worse", not "better")."""
CSV_NAME, METRICS_NAME = "episodes.csv", "metrics.json"
CSV_FIELDS = (
    "distribution", "run", "seed", "episode", "p", "direction", "start_row", "start_col",
    "return_averaging", "return_options", "return_interruption", "return_averaging_null",
    "interruptions", "exact_averaging", "exact_options", "exact_interruption",
)  # fmt: skip
FIGURES = {"train": "fig2_train.png", "south_only": "fig2_south_only.png"}
HEATMAP = "interruptions_heatmap.png"


def default_config_path() -> Path:
    """``configs/windy.yaml`` of the repository (or of the working directory)."""
    here = Path(__file__).resolve().parents[2] / "configs" / "windy.yaml"
    return here if here.is_file() else Path("configs") / "windy.yaml"


def test_seed(cfg: Config, run: int) -> int:
    """Seed of test run ``run``: ``cfg.seed + 1 + run`` (never the training seed)."""
    return int(cfg.seed) + 1 + int(run)


# --------------------------------------------------------------------------------------------
# paired evaluation


def make_eval_env(
    cfg: Config,
    instances: str | WindyInstances,
    num_envs: int,
    seed: int,
    index_offset: int = 0,
    noise_seed: int = 0,
) -> WindyGridEnv:
    """The family env of ``cfg`` on a test distribution; sub-env ``i`` is global episode ``offset + i``."""
    return make_env(
        cfg,
        num_envs,
        seed=seed,
        index_offset=index_offset,
        instances=instances,
        noise_seed=noise_seed,
        validate_actions=False,
    )


def build_controller(method: str, heads: Heads, cfg: Config) -> Controller:
    """A controller of ``method`` on ``heads`` with the family's option terminations."""

    if method == "hierarchy":
        raise ValueError(
            "method 'hierarchy' needs robustness heads and a composition hierarchy, which the "
            f"{cfg.family!r} bundle does not have; use averaging, options or interruption"
        )
    subtasks = make_subtasks(cfg, make_env(cfg, num_envs=1))
    return make_controller(method, heads, subtasks, seed=cfg.seed)


def evaluate(
    heads: Heads,
    cfg: Config,
    method: str,
    instances: str | WindyInstances,
    seed: int,
    episodes: int,
    batch_size: int | None = None,
    noise_seed: int = 0,
    record_firings: bool = False,
    progress: Any = None,
) -> dict[str, np.ndarray]:
    """Play ``episodes`` one-episode sub-envs (global indices ``0..episodes-1``) with ``method``.

    The same ``(seed, instances)`` gives every method the same instance and start per episode, and
    the same gusts when ``noise_seed`` matches: the pairing of docs/windy-fig2.md. The env is seeded
    per sub-env, so the result does not depend on ``batch_size``.

    Returns per-episode arrays ``return``, ``length``, ``interruptions``, ``p``, ``direction``,
    ``start`` and, with ``record_firings``, the firing events ``fire_episode``, ``fire_cell``,
    ``fire_option`` (the option running when Algorithm 1 line 6 fired).
    """
    ctrl = build_controller(method, heads, cfg)
    bs = int(batch_size or cfg.eval.batch_size)
    trace = (keys.CELL, keys.RUNNING_OPTION, keys.INTERRUPTED) if record_firings else ()
    parts: dict[str, list[np.ndarray]] = {}
    for lo in range(0, int(episodes), bs):
        n = min(bs, int(episodes) - lo)
        env = TransformedEnv(make_eval_env(cfg, instances, n, seed, lo, noise_seed), ctrl.primer())
        out = run_episodes(env, ctrl, max_steps=cfg.env.horizon, trace_keys=trace)
        got = {
            "return": out["return"],
            "length": out["length"],
            "interruptions": out["interruptions"],
            "p": out[keys.INSTANCE, "p"],
            "direction": out[keys.INSTANCE, "direction"],
            "start": out["start"],
        }
        if record_firings:
            tr = out["trace"]
            fired = tr[keys.INTERRUPTED].bool() & tr["alive"]  # (n, T)
            ep, _t = fired.nonzero(as_tuple=True)
            got["fire_episode"] = ep + lo
            got["fire_cell"] = tr[keys.CELL][fired]
            got["fire_option"] = tr[keys.RUNNING_OPTION][fired]
        for k, v in got.items():
            parts.setdefault(k, []).append(v.detach().cpu().numpy())
        if progress is not None:
            progress.update(n)
    return {k: np.concatenate(v) for k, v in parts.items()}


# --------------------------------------------------------------------------------------------
# exact figures (oracle)


def make_oracle(cfg: Config):
    """The exact oracle of ``cfg``'s layout, or ``None`` when the layout is too large."""

    layout = windy_layout(cfg.env)
    if layout.num_cells > EXACT_MAX_CELLS:
        return None
    return WindyOracle(layout, gamma=cfg.train.gamma, horizon=cfg.env.horizon)


def theorem1_check(
    oracle,
    options_ctrl: Controller,
    cfg: Config,
    rolls: dict[str, np.ndarray],
    exact_diff_vs_options: np.ndarray | None,
    diff_vs_averaging: np.ndarray,
    chunk: int = 1000,
) -> dict[str, Any]:
    """Theorem 1's premise at every state where interruption fired, and the outcome per case.

    At a firing (s', o) in test instance m: premise ``V^{mu_bar}(s') <= V^{m,mu_bar}(s')`` (learnt
    switching value vs the exact discounted value of the learnt options controller in m); the
    proof's condition ``Q^{m,mu_bar}(s', o) <= V^{m,mu_bar}(s')``; and the max-value assumption
    ``Q^{m,mu_bar}(s', o) <= Q_hat(s', o)``. Outcomes per episode group (premise held at every
    firing / failed at some): interruption - options (exact, what the theorem bounds) and
    interruption - averaging (sampled, paired). The values come from
    :func:`~taskvar_torch.oracle.learnt.firing_values`.
    """
    ep = rolls["fire_episode"]
    if ep.size == 0:
        return {"firings": 0, "episodes_with_firing": 0}
    vals = firing_values(oracle, options_ctrl, cfg.env.obs_encoding, rolls, chunk)
    v_m, q_m = vals["v_m"], vals["q_m"]
    episodes = np.unique(ep)
    premise = vals["v_mu_bar"] <= v_m + 1e-9
    proof_condition = q_m <= v_m + 1e-9
    max_assumption = q_m <= vals["q_hat"] + 1e-9
    failed = np.zeros(rolls["return"].size, dtype=bool)
    np.logical_or.at(failed, ep, ~premise)
    fired = np.zeros_like(failed)
    fired[episodes] = True

    def outcome(mask: np.ndarray) -> dict[str, Any]:
        o: dict[str, Any] = {"episodes": int(mask.sum())}
        if mask.any():
            o["vs_averaging_sampled"] = _short(
                paired_summary(torch.as_tensor(diff_vs_averaging[mask]))
            )
            if exact_diff_vs_options is not None:
                o["vs_options_exact"] = _short(_exact_summary(exact_diff_vs_options[mask]))
        return o

    return {
        "firings": int(ep.size),
        "episodes_with_firing": int(episodes.size),
        "premise_held": int(premise.sum()),
        "premise_held_fraction": float(premise.mean()),
        "proof_condition_held": int(proof_condition.sum()),
        "proof_condition_held_fraction": float(proof_condition.mean()),
        "max_value_assumption_held_fraction": float(max_assumption.mean()),
        "outcome_premise_held_at_every_firing": outcome(fired & ~failed),
        "outcome_premise_failed_somewhere": outcome(fired & failed),
        "note": "values discounted with train.gamma; V^{m,mu_bar} = learnt options controller in m",
    }


def _short(summary: dict[str, float]) -> dict[str, float]:
    return {
        k: summary[k]
        for k in (
            "fraction_no_worse",
            "fraction_better",
            "fraction_worse",
            "mean_difference",
            "mean_difference_ci95",
        )
    }


def _exact_summary(diff: np.ndarray) -> dict[str, float]:
    """``paired_summary`` of exact expected-return differences, ties within ``EXACT_ATOL``."""
    d = np.where(np.abs(diff) <= EXACT_ATOL, 0.0, diff)
    return paired_summary(torch.as_tensor(d))


# --------------------------------------------------------------------------------------------
# one test distribution


def run_distribution(
    heads: Heads,
    cfg: Config,
    instances: str,
    runs: int,
    episodes: int,
    oracle=None,
    progress: bool = True,
    desc: str = "",
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Every method on R paired runs of E episodes of one test distribution; metrics and CSV rows."""
    rows: list[dict[str, Any]] = []
    per_run: list[dict[str, Any]] = []
    pooled: dict[str, list[np.ndarray]] = {}
    fire_parts: dict[str, list[np.ndarray]] = {}
    width = windy_layout(cfg.env).width
    ctrls = {m: build_controller(m, heads, cfg) for m in METHODS} if oracle is not None else {}
    bar = tqdm(
        total=runs * episodes * (len(METHODS) + 1), disable=not progress, desc=desc, unit="ep"
    )
    for run in range(runs):
        seed = test_seed(cfg, run)
        r = {
            m: evaluate(
                heads,
                cfg,
                m,
                instances,
                seed,
                episodes,
                record_firings=m == "interruption",
                progress=bar,
            )
            for m in METHODS
        }
        null = evaluate(
            heads,
            cfg,
            "averaging",
            instances,
            seed,
            episodes,
            noise_seed=NULL_NOISE_SEED,
            progress=bar,
        )
        base = r["averaging"]
        for m in METHODS:  # the pairing: same instances and starts for every method
            assert np.array_equal(r[m]["p"], base["p"]) and np.array_equal(
                r[m]["start"], base["start"]
            )
        ex = {}
        if oracle is not None:
            for m in METHODS:
                ex[m] = exact_returns(
                    oracle, ctrls[m], cfg, base["p"], base["direction"], base["start"]
                )
        cols = {
            "return_averaging": base["return"],
            "return_options": r["options"]["return"],
            "return_interruption": r["interruption"]["return"],
            "return_averaging_null": null["return"],
            "interruptions": r["interruption"]["interruptions"],
            **{f"exact_{m}": v for m, v in ex.items()},
        }
        for k, v in cols.items():
            pooled.setdefault(k, []).append(v)
        roll = r["interruption"]
        for k in ("fire_episode", "fire_cell", "fire_option"):
            fire_parts.setdefault(k, []).append(
                roll[k] + (run * episodes if k == "fire_episode" else 0)
            )
        for k in ("p", "direction", "start"):
            pooled.setdefault(k, []).append(base[k])
        diff = torch.as_tensor(cols["return_interruption"] - cols["return_averaging"])
        per_run.append(
            {
                "run": run,
                "seed": seed,
                **_short(paired_summary(diff)),
                "fraction_no_worse_null": float(
                    np.mean(cols["return_averaging"] >= cols["return_averaging_null"])
                ),
                "mean_return": {
                    m: float(np.mean(r[m]["return"], dtype=np.float64)) for m in METHODS
                },
                "interruptions_per_episode": float(np.mean(cols["interruptions"])),
            }
        )
        start_row, start_col = np.divmod(base["start"], width)
        for i in range(episodes):
            row = {
                "distribution": desc,
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
    bar.close()
    data = {k: np.concatenate(v) for k, v in pooled.items()}
    fires = {k: np.concatenate(v) for k, v in fire_parts.items()}
    metrics = summarise(data, fires, cfg, runs, episodes)
    metrics["per_run"] = per_run
    if oracle is not None:
        rolls = {
            "return": data["return_averaging"],
            "p": data["p"],
            "direction": data["direction"],
            **fires,
        }
        metrics["theorem1"] = theorem1_check(
            oracle,
            ctrls["options"],
            cfg,
            rolls,
            data["exact_interruption"] - data["exact_options"],
            data["return_interruption"] - data["return_averaging"],
        )
    else:
        metrics["theorem1"] = None
    return metrics, rows


def summarise(
    data: dict[str, np.ndarray], fires: dict[str, np.ndarray], cfg: Config, runs: int, episodes: int
) -> dict[str, Any]:
    """Figure 2's numbers for one distribution from the pooled per-episode columns."""
    t = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in data.items()}
    main = paired_summary(t["return_interruption"] - t["return_averaging"])
    null = paired_summary(t["return_averaging"] - t["return_averaging_null"])
    m: dict[str, Any] = {**main, "runs": runs, "episodes_per_run": episodes}
    m["fraction_no_worse_null"] = null["fraction_no_worse"]
    m["null"] = _short(null)
    m["options_vs_averaging"] = _short(paired_summary(t["return_options"] - t["return_averaging"]))
    m["interruption_vs_options"] = _short(
        paired_summary(t["return_interruption"] - t["return_options"])
    )
    m["mean_return"] = {}
    for name in (*METHODS, "averaging_null"):
        mean, ci = mean_ci95(t[f"return_{name}"])
        m["mean_return"][name] = {"mean": mean, "ci95": ci}
    if "exact_interruption" in data:
        ex = _exact_summary(data["exact_interruption"] - data["exact_averaging"])
        m["fraction_no_worse_exact"] = ex["fraction_no_worse"]
        m["exact"] = {
            **_short(ex),
            "options_vs_averaging": _short(
                _exact_summary(data["exact_options"] - data["exact_averaging"])
            ),
            "interruption_vs_options": _short(
                _exact_summary(data["exact_interruption"] - data["exact_options"])
            ),
            "mean_return": {n: float(data[f"exact_{n}"].mean()) for n in METHODS},
            "note": "exact expected returns of the learnt controllers in each episode's (instance, start)",
        }
    else:
        m["fraction_no_worse_exact"] = None
        m["exact"] = None
    k = data["interruptions"].astype(np.float64)
    S = windy_layout(cfg.env).num_cells
    m["interruptions_per_episode"] = float(k.mean())
    m["episodes_with_interruption"] = float((k > 0).mean())
    m["interruption_cells"] = np.bincount(fires["fire_cell"], minlength=S).astype(int).tolist()
    opts = np.bincount(fires["fire_option"], minlength=2)
    m["interruptions_by_running_option"] = opts.astype(int).tolist()
    return m


# --------------------------------------------------------------------------------------------
# the experiment


def windy_fig2(
    cfg: Config,
    out_dir: str | os.PathLike,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = True,
    quick: bool = False,
    plots: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train (or load ``checkpoint``), evaluate Figure 2's protocol, write the results folder.

    Args:
        cfg: a windy config; ``experiment.runs`` x ``experiment.episodes_per_run`` test episodes
            per distribution, ``eval.batch_size`` environments in parallel.
        out_dir: results folder (created).
        checkpoint: a bundle written by ``train.train``; skips training (its config's env and
            heads are used, ``cfg``'s experiment and eval sizes).
        progress: tqdm progress bars.
        quick: recorded in ``metrics.json`` (the config already holds the quick overrides).
        plots: draw the PNGs (``False``: skip them, e.g. in sweeps; ``taskvar plot DIR`` draws
            them later from the folder).
        overwrite: replace a training run already in ``out_dir/train`` (without it such a folder
            is refused, see :func:`~taskvar_torch.train.train`).

    Returns:
        The metrics dict written to ``metrics.json``.
    """

    FAMILIES["windy"].require(cfg, "windy-fig2")
    out = Path(out_dir)
    check_output_folder(out)  # every check before any work or any file written
    check_device(cfg.device)
    heads = tcfg = None
    if checkpoint is not None:
        saved = load_checkpoint(checkpoint)["config"].get("family")
        if saved not in FAMILIES or FAMILIES[saved].experiment != "windy-fig2":
            raise ValueError(
                f"--checkpoint {str(checkpoint)!r} is a {saved!r} bundle; windy-fig2 "
                "evaluates windy bundles (wargus-fig4 trains its own)"
            )
        heads, tcfg = load_heads(checkpoint, device=cfg.device)
    elif run_files(out / "train") and not overwrite:
        raise ValueError(
            f"{str(out / 'train')!r} already holds a training run; replace it with --overwrite, "
            f"evaluate it with --checkpoint {out / 'train' / 'final.pt'}, or choose another --out"
        )
    refuse_existing_results(out, overwrite, "taskvar experiment windy-fig2")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    train_seconds = 0.0
    if checkpoint is None:
        save_config_yaml(cfg, out / "config.yaml")
        result = train(cfg, out / "train", progress=progress, overwrite=overwrite)
        checkpoint, train_seconds = result["final"], float(result["seconds"])
        heads, tcfg = load_heads(checkpoint, device=cfg.device)
    else:
        tcfg = _with_sizes(tcfg, cfg)
        save_config_yaml(tcfg, out / "config.yaml")
    cfg = tcfg
    runs, episodes = cfg.experiment.runs, cfg.experiment.episodes_per_run
    oracle = make_oracle(cfg)
    metrics: dict[str, Any] = {
        "experiment": "windy-fig2",
        "quick": bool(quick),
        "layout": cfg.env.layout,
        "checkpoint": str(checkpoint),
        "seeds": [test_seed(cfg, r) for r in range(runs)],
        "null_noise_seed": NULL_NOISE_SEED,
        "methods": list(METHODS),
        "comparison": "interruption - averaging (paired: same instance, start and gusts)",
    }
    all_rows: list[dict[str, Any]] = []
    eval_t0 = time.perf_counter()
    for key, instances in DISTRIBUTIONS.items():
        m, rows = run_distribution(
            heads, cfg, instances, runs, episodes, oracle, progress, desc=key
        )
        all_rows += rows
        if key == "train":
            metrics.update(m)
        else:
            metrics[key] = m
    metrics["oracle_by_start"] = learnt_vs_oracle_by_start(heads, oracle)
    metrics["train_seconds"] = train_seconds
    metrics["eval_seconds"] = time.perf_counter() - eval_t0
    metrics["wall_seconds"] = time.perf_counter() - t0
    write_csv(out / CSV_NAME, all_rows, CSV_FIELDS)
    write_json(out / METRICS_NAME, metrics)
    figures = [str(p) for p in plot_results(out)] if plots else []
    print(format_table(metrics))
    print(format_start_table(metrics["oracle_by_start"]))
    print(
        f"wrote {out / METRICS_NAME}, {out / CSV_NAME}"
        + "".join(f", {f}" for f in figures)
        + ("" if plots else f" (no plots: taskvar plot {out})")
    )
    return metrics


def _with_sizes(ckpt_cfg: Config, cfg: Config) -> Config:
    """The checkpoint's config with ``cfg``'s experiment and eval sections (sizes of this run)."""

    return dataclasses.replace(ckpt_cfg, experiment=cfg.experiment, eval=cfg.eval)


# --------------------------------------------------------------------------------------------
# table and plots


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

    for dist, m in (("train", metrics), ("south_only", metrics.get("south_only"))):
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
        for d, m in (("train", metrics), ("south_only", metrics.get("south_only")))
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
            windy_layout(cfg.env),
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


# --------------------------------------------------------------------------------------------
# checkpoint-based evaluation


def eval_checkpoint(
    checkpoint: str | os.PathLike,
    method: str,
    episodes: int,
    test: str,
    out_dir: str | os.PathLike | None = None,
    seed: int | None = None,
    noise_seed: int = 0,
    progress: bool = True,
) -> dict[str, Any]:
    """Evaluate a saved windy bundle with ``method`` on test distribution ``test``; no retraining.

    :func:`~taskvar_torch.experiments.bundle_eval.eval_bundle` with one method and no shift (no
    plot): ``seed`` defaults to :func:`test_seed` of run 0, so ``windy_fig2``'s run ``r`` (seed
    ``cfg.seed + 1 + r``, ``episodes_per_run`` episodes) is reproduced exactly by the same seed,
    episodes and method. Writes ``out_dir/metrics.json`` (and ``episodes.csv``) when given.
    """
    return eval_bundle(
        checkpoint,
        method,
        test,
        episodes=episodes,
        seed=seed,
        noise_seed=noise_seed,
        out_dir=out_dir,
        progress=progress,
        plots=False,
    )
