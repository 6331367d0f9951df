"""Windy Figure 2 with the learnt networks (paper §3.3.1; docs/windy-fig2.md).

:func:`windy_fig2` trains (or loads) the heads, plays the averaging, options and interruption
(Algorithm 1) controllers on paired rollouts of each test distribution and the sealed held-out
episodes, and writes the results folder (docs/windy-fig2.md#outputs). Metrics live in
:mod:`.fig2_metrics`, tables and plots in :mod:`.fig2_report`.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from taskvar_torch import keys
from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import Config, save_config_yaml
from taskvar_torch.config.memory import check_memory
from taskvar_torch.config.memory import estimate as estimate_memory
from taskvar_torch.contract import FAMILIES, HELDOUT_SEED, HELDOUT_SIZE, sealed_episode_seed
from taskvar_torch.controllers import Controller, make_controller
from taskvar_torch.experiments.bundle_eval import eval_bundle
from taskvar_torch.experiments.paired import play
from taskvar_torch.experiments.results import code_version, write_csv, write_json
from taskvar_torch.experiments.shift import EvalPoint
from taskvar_torch.factory import check_device, load_heads, make_env, make_subtasks
from taskvar_torch.families.windy import (
    WindyOracle,
    exact_returns,
    learnt_vs_oracle_by_start,
)
from taskvar_torch.families.windy.config import section
from taskvar_torch.families.windy.env import WindyGridEnv
from taskvar_torch.families.windy.family import EXACT_ORACLE_CELLS, windy_layout
from taskvar_torch.families.windy.fig2_metrics import (
    METHODS,
    run_summary,
    summarise,
    theorem1_check,
)
from taskvar_torch.families.windy.fig2_report import (
    CSV_FIELDS,
    CSV_NAME,
    METRICS_NAME,
    csv_rows,
    format_start_table,
    format_table,
    plot_results,
)
from taskvar_torch.families.windy.instances import WindyInstances
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import (
    RESULT_MARKERS,
    ResultsFolder,
    check_output_folder,
    refuse_inside,
    run_files,
)
from taskvar_torch.training import train

DISTRIBUTIONS = {"train": "train", "south_only": "south"}
"""metrics.json key -> test instance distribution (``train``: the training distribution)."""
HELDOUT = {"heldout": "train"}
"""metrics.json key -> the sealed held-out test: the training distribution under the held-out
seeds, drawn apart per training seed (:func:`heldout_seed`; ``taskvar eval --test heldout`` with
``--episodes experiment.episodes_per_run`` replays its run 0 exactly)."""
NULL_NOISE_SEED = 1
"""Gust-stream salt of the null comparison's second averaging rollout (same instances, starts)."""
EXACT_MAX_CELLS = EXACT_ORACLE_CELLS
"""The exact figure is computed on layouts with at most this many cells (the family registry's
exact-oracle limit)."""


def default_config_path() -> Path:
    """``configs/windy.yaml`` of the repository (or of the working directory)."""
    here = Path(__file__).resolve().parents[3] / "configs" / "windy.yaml"
    return here if here.is_file() else Path("configs") / "windy.yaml"


def test_seed(cfg: Config, run: int) -> int:
    """Seed of test run ``run``: ``cfg.seed + 1 + run`` (never the training seed)."""
    return int(cfg.seed) + 1 + int(run)


def heldout_seed(cfg: Config, run: int) -> int:
    """Seed of held-out run ``run``: ``HELDOUT_SEED + run`` sealed apart per training seed
    (:func:`~taskvar_torch.families.sealed_episode_seed`); run 0 is ``taskvar eval --test
    heldout``'s."""
    if not 0 <= int(run) < HELDOUT_SIZE:
        raise ValueError(f"experiment.runs must be at most {HELDOUT_SIZE} (the held-out seeds)")
    return sealed_episode_seed(HELDOUT_SEED + int(run), int(cfg.seed))


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
    """Play ``episodes`` episodes with ``method`` through the one episode player
    (:func:`~taskvar_torch.experiments.paired.play`), paired by ``(seed, instances, noise_seed)``.

    Returns per-episode arrays ``return``, ``length``, ``interruptions``, ``p``, ``direction``,
    ``start`` and, with ``record_firings``, ``fire_episode``, ``fire_cell``, ``fire_option``.
    """
    ctrl = build_controller(method, heads, cfg)
    bs = int(batch_size or cfg.eval.batch_size)
    traced = (keys.CELL, keys.RUNNING_OPTION, keys.INTERRUPTED) if record_firings else ()
    point = EvalPoint("", None, cfg, instances)
    r = play(ctrl, point, episodes, seed, bs, noise_seed, progress, steps=traced)
    got = {k: r[k] for k in ("return", "length", "interruptions", "start")}
    got["p"], got["direction"] = r["instance_p"], r["instance_direction"]
    if record_firings:
        fired = r[f"step_{keys.INTERRUPTED}"].astype(bool) & r["step_alive"]  # (E, T)
        got["fire_episode"] = fired.nonzero()[0]
        got["fire_cell"] = r[f"step_{keys.CELL}"][fired]
        got["fire_option"] = r[f"step_{keys.RUNNING_OPTION}"][fired]
    return got


# --------------------------------------------------------------------------------------------
# exact figures (oracle)


def make_oracle(cfg: Config):
    """The exact oracle of ``cfg``'s layout, or ``None`` when the layout is too large."""

    layout = windy_layout(section(cfg))
    if layout.num_cells > EXACT_MAX_CELLS:
        return None
    return WindyOracle(layout, gamma=cfg.train.gamma, horizon=section(cfg).horizon)


# --------------------------------------------------------------------------------------------
# one test distribution


def play_run(
    heads: Heads, cfg: Config, instances: str, seed: int, episodes: int, bar: Any = None
) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, np.ndarray]]:
    """One run's paired rollouts: every method of :data:`METHODS`, then the null averaging rollout;
    returns ``({method: evaluate(...)}, null)`` and asserts the pairing.
    """
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
        assert np.array_equal(r[m]["p"], base["p"]) and np.array_equal(r[m]["start"], base["start"])
    return r, null


def episode_columns(
    r: dict[str, dict[str, np.ndarray]],
    null: dict[str, np.ndarray],
    exact: dict[str, np.ndarray],
) -> dict[str, np.ndarray]:
    """One run's per-episode columns of ``episodes.csv`` (besides instance and start): each
    method's return, the null return, interruptions and the ``exact`` returns per method (step 5;
    empty without an oracle)."""
    return {
        "return_averaging": r["averaging"]["return"],
        "return_options": r["options"]["return"],
        "return_interruption": r["interruption"]["return"],
        "return_averaging_null": null["return"],
        "interruptions": r["interruption"]["interruptions"],
        **{f"exact_{m}": v for m, v in exact.items()},
    }


def run_distribution(
    heads: Heads,
    cfg: Config,
    instances: str,
    runs: int,
    episodes: int,
    oracle=None,
    progress: bool = True,
    desc: str = "",
    seed_of: Any = test_seed,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Every method on R paired runs of E episodes of one test distribution (run ``r`` plays
    ``seed_of(cfg, r)``): per-run summaries, CSV rows, pooled metrics and Theorem 1's check.
    """
    rows: list[dict[str, Any]] = []
    per_run: list[dict[str, Any]] = []
    pooled: dict[str, list[np.ndarray]] = {}
    fire_parts: dict[str, list[np.ndarray]] = {}
    width = windy_layout(section(cfg)).width
    ctrls = {m: build_controller(m, heads, cfg) for m in METHODS} if oracle is not None else {}
    bar = progress_bar(
        total=runs * episodes * (len(METHODS) + 1), disable=not progress, desc=desc, unit="ep"
    )
    for run in range(runs):
        seed = seed_of(cfg, run)
        r, null = play_run(heads, cfg, instances, seed, episodes, bar)
        base = r["averaging"]
        ex = {}
        if oracle is not None:
            for m in METHODS:
                ex[m] = exact_returns(
                    oracle, ctrls[m], cfg, base["p"], base["direction"], base["start"]
                )
        cols = episode_columns(r, null, ex)
        for k, v in cols.items():
            pooled.setdefault(k, []).append(v)
        roll = r["interruption"]
        for k in ("fire_episode", "fire_cell", "fire_option"):  # episode indices over all runs
            fire_parts.setdefault(k, []).append(
                roll[k] + (run * episodes if k == "fire_episode" else 0)
            )
        for k in ("p", "direction", "start"):
            pooled.setdefault(k, []).append(base[k])
        per_run.append(run_summary(run, seed, cols, r))
        rows += csv_rows(desc, run, seed, base, cols, width)
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
    staged: bool = True,
    controller: Sequence[str] = (),
) -> dict[str, Any]:
    """Train (or load ``checkpoint``), evaluate Figure 2's protocol, write ``out_dir``.

    Args:
        cfg: a windy config (``experiment.runs`` x ``experiment.episodes_per_run`` episodes).
        out_dir: results folder (:class:`~taskvar_torch.run_folder.ResultsFolder`); training goes
            to ``out_dir/train``.
        checkpoint: a bundle from ``train.train``; skips training.
        progress: progress bars. quick: recorded in ``metrics.json``. plots: draw the PNGs.
        overwrite: replace results already in ``out_dir`` (otherwise refused).
        controller: controller settings (``config/controller.py``).
        staged: ``False`` writes into ``out_dir`` directly (a sweep's point).

    Returns:
        The metrics dict written to ``metrics.json``.
    """

    FAMILIES["windy"].require(cfg, "windy-fig2")
    if controller and checkpoint is None:
        raise ValueError(
            "controller settings apply to a --checkpoint; to train, override the config"
        )
    heldout_seed(cfg, cfg.experiment.runs - 1)  # every held-out run has a sealed seed
    if not staged:
        out = Path(out_dir)
        heads, tcfg = _check_inputs(
            cfg, out, checkpoint, overwrite=overwrite, controller=controller
        )
        out.mkdir(parents=True, exist_ok=True)
        return _windy_fig2(
            cfg, out, out, checkpoint, heads, tcfg, progress, quick, plots, overwrite
        )  # fmt: skip
    folder = ResultsFolder(out_dir, overwrite, "taskvar experiment windy-fig2")
    heads, tcfg = _check_inputs(cfg, folder.out, checkpoint, folder=folder, controller=controller)
    with folder as staging:  # locked; written in a staging folder, swapped in whole at the end
        return _windy_fig2(
            cfg, folder.out, staging, checkpoint, heads, tcfg, progress, quick, plots, False
        )  # fmt: skip


def _windy_fig2(
    cfg: Config,
    dest: Path,
    out: Path,
    checkpoint: str | os.PathLike | None,
    heads: Heads | None,
    tcfg: Config | None,
    progress: bool,
    quick: bool,
    plots: bool,
    overwrite: bool,
) -> dict[str, Any]:
    """:func:`windy_fig2` writing into ``out`` (``dest``, or the staging folder of ``dest``)."""
    t0 = time.perf_counter()
    train_seconds = 0.0
    if checkpoint is None:
        save_config_yaml(cfg, out / "config.yaml")
        result = train(cfg, out / "train", progress=progress, overwrite=overwrite)
        train_seconds = float(result["seconds"])
        heads, tcfg = load_heads(result["final"], device=cfg.device)
        checkpoint = dest / "train" / "final.pt"  # where it is once the folder is swapped in
    else:
        tcfg = _with_sizes(tcfg, cfg)
        save_config_yaml(tcfg, out / "config.yaml")
    cfg = tcfg
    runs, episodes = cfg.experiment.runs, cfg.experiment.episodes_per_run
    oracle = make_oracle(cfg)
    metrics: dict[str, Any] = {
        "experiment": "windy-fig2",
        "code": code_version(),
        "quick": bool(quick),
        "layout": section(cfg).layout,
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
    for key, instances in HELDOUT.items():  # the sealed held-out episodes, beside the nominal
        m, rows = run_distribution(
            heads, cfg, instances, runs, episodes, oracle, progress, key, heldout_seed
        )
        all_rows += rows
        metrics[key] = m
        metrics[key]["seeds"] = [heldout_seed(cfg, r) for r in range(runs)]
    metrics["oracle_by_start"] = learnt_vs_oracle_by_start(heads, oracle)
    metrics["train_seconds"] = train_seconds
    metrics["eval_seconds"] = time.perf_counter() - eval_t0
    metrics["wall_seconds"] = time.perf_counter() - t0
    _write_results(out, metrics, all_rows, plots, shown=dest)
    return metrics


def _check_inputs(
    cfg: Config,
    out: Path,
    checkpoint: str | os.PathLike | None,
    folder: ResultsFolder | None = None,
    overwrite: bool = False,
    controller: Sequence[str] = (),
) -> tuple[Heads | None, Config | None]:
    """Every check before any work: output folder, device, memory, the checkpoint's family and
    place. Returns the checkpoint's ``(heads, config)`` or ``(None, None)``."""
    check_output_folder(out)
    has_results = any((out / m).is_file() for m in RESULT_MARKERS)
    if checkpoint is None and run_files(out / "train") and not (has_results or overwrite):
        raise ValueError(
            f"{str(out / 'train')!r} already holds a training run; evaluate it with --checkpoint "
            f"{out / 'train' / 'final.pt'}, or choose another --out"
        )
    if folder is not None:
        folder.check()
        if checkpoint is not None:
            refuse_inside(checkpoint, out, "--checkpoint")
    check_device(cfg.device)
    x = cfg.experiment  # one result row per test episode, distribution and method
    rows = (len(DISTRIBUTIONS) + len(HELDOUT)) * x.runs * x.episodes_per_run * len(METHODS)
    key = "experiment.episodes_per_run"
    check_memory(estimate_memory(cfg, training=False, episodes=rows, episodes_key=key))
    heads = tcfg = None
    if checkpoint is not None:
        saved = load_checkpoint(checkpoint)["config"].get("family")
        own = FAMILIES[saved].experiment if saved in FAMILIES else None
        if own is None or own.name != "windy-fig2":
            raise ValueError(
                f"--checkpoint {str(checkpoint)!r} is a {saved!r} bundle; windy-fig2 "
                "evaluates windy bundles (wargus-fig4 trains its own)"
            )
        heads, tcfg = load_heads(checkpoint, device=cfg.device, controller=controller)
    return heads, tcfg


def _write_results(
    out: Path,
    metrics: dict[str, Any],
    rows: list[dict[str, Any]],
    plots: bool,
    shown: Path | None = None,
) -> None:
    """Write ``episodes.csv``, ``metrics.json`` and (with ``plots``) the figures; print the
    tables and what was written, named where it will be (``shown``: the folder ``out`` stages)."""
    write_csv(out / CSV_NAME, rows, CSV_FIELDS)
    write_json(out / METRICS_NAME, metrics)
    figures = [p.relative_to(out) for p in plot_results(out)] if plots else []
    where = out if shown is None else shown
    print(format_table(metrics))
    print(format_start_table(metrics["oracle_by_start"]))
    print(
        f"wrote {where / METRICS_NAME}, {where / CSV_NAME}"
        + "".join(f", {where / f}" for f in figures)
        + ("" if plots else f" (no plots: taskvar plot {where})")
    )


def _with_sizes(ckpt_cfg: Config, cfg: Config) -> Config:
    """The checkpoint's config with ``cfg``'s experiment and eval sections (sizes of this run)."""

    return dataclasses.replace(ckpt_cfg, experiment=cfg.experiment, eval=cfg.eval)


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
    """Evaluate a saved windy bundle with ``method`` on ``test`` without retraining
    (:func:`~taskvar_torch.experiments.bundle_eval.eval_bundle`); the default ``seed`` reproduces
    ``windy_fig2``'s run 0. Writes ``out_dir/metrics.json`` (and ``episodes.csv``) when given.
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
        overwrite=False,  # a folder holding results is refused
    )


__all__ = [  # the protocol, and the registry's plot (experiments/registry.py)
    "DISTRIBUTIONS",
    "EXACT_MAX_CELLS",
    "HELDOUT",
    "NULL_NOISE_SEED",
    "build_controller",
    "default_config_path",
    "episode_columns",
    "eval_checkpoint",
    "evaluate",
    "heldout_seed",
    "make_eval_env",
    "make_oracle",
    "play_run",
    "plot_results",
    "run_distribution",
    "test_seed",
    "windy_fig2",
]
