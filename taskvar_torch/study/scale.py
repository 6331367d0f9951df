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

Held-out (``heldout_episodes``, default ``eval_episodes``; 0: off): every cell also plays the same
methods on the family's sealed held-out test distribution (``Family.tests["heldout"]``: windy
and Taxi the training distribution under env seed ``HELDOUT_SEED`` itself, Wargus the held-out
instance seeds ``HELDOUT_SEEDS``, cycled; the same episodes for every seed, like the nominal test
seed, where ``taskvar eval --test heldout`` draws each bundle's own), paired across methods, with the random policy and the exact averaging optimum (where the family has one)
on the same held-out episodes; new keys only (:func:`heldout_block`): ``metrics["heldout"]`` (the
distribution, its seed, the references per case) and each cell's ``heldout`` (``methods``, like
the cell's own, and with ``seeds > 1`` ``per_seed`` and ``over_seeds``). It draws no random number
the nominal evaluation uses (:func:`isolated_rng`), so every other value is what it was without it.

Baselines (``baselines``, default none; docs/scale.md#baselines): each cell (each seed's bundle
folder) also trains the listed baselines of docs/memory.md (``recurrent``, ``informed``) with
``train_recurrent.train_baseline`` on the cell's own config and frame budget, as ``taskvar
train-baselines`` does, and plays them on the same test episodes (and held-out ones) as new
``methods`` entries (:func:`baseline_phase`), under :func:`isolated_rng`: the methods' values are
unchanged. A family a listed baseline is unavailable on (``informed`` where the family gives no
features) is refused before any training (:func:`check_case_baselines`).

Writes ``config.yaml`` (this experiment's config), ``cells/<case>-n<N>/`` (the trainer's logs and
config; ``final.pt`` only with ``keep_checkpoints``), ``scale.csv`` (one row per cell and method),
``metrics.json``, ``scale.png``; prints a table. ``taskvar plot OUT`` redraws ``scale.png``.

Seeds (``seeds = k > 1``): each cell is trained *once* with ``train.seeds = k`` (the batched
trainer, docs/seeds.md: training seeds ``seed .. seed + k - 1``, bundles in
``cells/<case>-n<N>/seed<i>/``) and every seed's bundle is evaluated on the same test episodes.
A cell's existing keys (``methods``, ``curve``, ``heads``) are then seed ``seed``'s run (the
learning curve and the exact head report of seed 0 only: per seed they would cost k times the
evaluation); new keys hold the rest: ``seeds``, ``per_seed`` (every seed's methods) and
``over_seeds`` (each method's mean return over the seeds with rliable's stratified-bootstrap 95%
CI, :func:`over_seeds`); ``scale.csv`` gets a ``seed`` column and one row per seed; the printed
table adds each cell's aggregate, and ``scale.png``'s final-return panels draw it.

This module is the protocol (:func:`scale`) and the registry's entry points (the loader, the
default config); the config is :mod:`taskvar_torch.study.scale_config`, the evaluation and
the references :mod:`taskvar_torch.study.scale_eval`, one cell (training, seeds, baselines,
held-out block) :mod:`taskvar_torch.study.scale_cell`, and the report (``scale.csv``'s rows,
the table, ``scale.png``) :mod:`taskvar_torch.study.scale_report`.

Examples:
    >>> cfg = load_scale_config(default_config_path(), quick=True)  # doctest: +SKIP
    >>> metrics = scale(cfg, "results/scale-quick")  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from taskvar_torch.config import (
    METHODS,
    load_strict,
    save_config_yaml,
)
from taskvar_torch.experiments.results import code_version, write_csv, write_json
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import ResultsFolder
from taskvar_torch.study.scale_cell import (
    heldout_references,
    run_cell,
)
from taskvar_torch.study.scale_config import (
    TEST_SEED_OFFSET,
    ScaleCase,
    ScaleConfig,
    case_config,
    check_case_baselines,
)
from taskvar_torch.study.scale_eval import (
    HELDOUT_TEST,
    references,
)
from taskvar_torch.study.scale_report import (
    CSV_NAME,
    EXPERIMENT,
    FIGURE,
    METRICS_NAME,
    csv_fields,
    csv_rows,
    format_table,
    plot_results,
)


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

    ``path`` may also be one family's config (a YAML with a top-level ``family``, any registered
    family's): it is then the one case (named by the file's stem) of the default scale config
    (:func:`default_config_path`: its budget, ``num_envs``, sizes and ``--quick`` overrides, but
    for their ``only``), e.g. ``taskvar experiment scale
    examples/corridor/configs/corridor.yaml --quick`` (docs/scale.md).

    Loading is :func:`taskvar_torch.config.load_strict`, the training configs' loader; the quick
    overrides are read (and checked) only with ``quick``.
    """
    path = Path(path)
    family_config = _is_family_config(path)
    cfg = load_strict(
        ScaleConfig,
        default_config_path() if family_config else path,
        overrides,
        quick=quick,
        quick_overrides=lambda c: (
            [o for o in c.quick_overrides if not o.startswith("only=")]
            if family_config
            else c.quick_overrides
        ),
        check_quick=False,
    )
    if family_config:  # the one case: a path as given (relative to the working directory)
        case = ScaleCase(name=path.stem, config=str(path.resolve()))
        cfg = dataclasses.replace(cfg, cases=[case], only=())
    cases = []
    for c in cfg.cases:
        p = Path(c.config)
        if not p.is_absolute():
            p = path.parent / p
        cases.append(dataclasses.replace(c, config=str(p)))
    cfg = dataclasses.replace(cfg, cases=cases)
    for c in cfg.selected():  # a typo in a case fails now, not after an hour
        check_case_baselines(cfg, c, case_config(cfg, c, cfg.num_envs[0]))
    return cfg


def _is_family_config(path: Path) -> bool:
    """Whether the YAML at ``path`` is a family config (a mapping with a top-level ``family``)
    rather than a scale config; an unreadable file is left to the strict loader's error."""
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and "family" in data


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
    folder is refused. ``out_dir`` is written like every results folder
    (:class:`~taskvar_torch.run_folder.ResultsFolder`: locked, filled in a staging folder and
    swapped in whole).

    Returns:
        The metrics dict written to ``metrics.json``.
    """
    folder = ResultsFolder(out_dir, overwrite, "taskvar experiment scale")
    with folder as staging:
        metrics = _scale(cfg, staging, progress, quick, plots)
    where = folder.out  # printed once the staging folder is swapped in
    print(
        f"wrote {where / METRICS_NAME}, {where / CSV_NAME}"
        + (f", {where / FIGURE}" if plots else "")
    )
    return metrics


def _scale(cfg: ScaleConfig, out: Path, progress: bool, quick: bool, plots: bool) -> dict[str, Any]:
    """:func:`scale` writing into the folder ``out``."""
    save_config_yaml(cfg, out / "config.yaml")
    t0 = time.perf_counter()
    cases = cfg.selected()
    refs: dict[str, Any] = {}
    held_refs: dict[str, Any] = {}
    cells: list[dict[str, Any]] = []
    if cfg.baselines:  # a baseline a family lacks fails before any training
        for case in cases:
            check_case_baselines(cfg, case, case_config(cfg, case, cfg.num_envs[0]))
    bar = progress_bar(
        total=len(cases) * len(cfg.num_envs), disable=not progress, desc="scale", unit="cell"
    )
    for case in cases:
        ccfg = case_config(cfg, case, cfg.num_envs[0])
        refs[case.name] = references(ccfg, cfg.eval_episodes, cfg.eval_batch_size)
        held = heldout_references(cfg, ccfg) if cfg.heldout_count() > 0 else None
        if held is not None:
            held_refs[case.name] = held
        for n in cfg.num_envs:
            bar.set_postfix_str(f"{case.name} N={n}")
            cells.append(run_cell(cfg, case, n, out, refs[case.name], False, held))  # new folder
            bar.update(1)
    bar.close()
    metrics = {
        "experiment": EXPERIMENT,
        "code": code_version(),
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
            "hierarchy": "n/a for a family without a composition hierarchy (windy, taxi)",
        },
    }
    if cfg.seeds > 1:  # new keys only: with one seed metrics.json is what it always was
        metrics["seeds"] = cfg.seeds
        metrics["notes"]["over_seeds"] = (
            "per cell: methods, curve and heads are seed `seed`'s run; per_seed holds every "
            "seed's methods on the same test episodes, over_seeds each method's mean over the "
            "seeds with rliable's stratified-bootstrap 95% CI [lo, hi] (mean_ci95)"
        )
    if cfg.baselines:  # new keys only: without baselines metrics.json is what it always was
        metrics["baselines"] = list(cfg.baselines)
        metrics["notes"]["baselines"] = (
            "per cell, methods (and per_seed, over_seeds, heldout) also hold the listed baselines "
            "(docs/memory.md), trained per seed on the cell's config and frame budget and played "
            "on the same test episodes; baseline_training, baseline_train_seconds: their training"
        )
    if held_refs:  # new keys only: with heldout_episodes=0 metrics.json is what it always was
        metrics["heldout"] = {
            "test": HELDOUT_TEST,
            "episodes": cfg.heldout_count(),
            "references": held_refs,
            "note": (
                "per cell, heldout holds every method on the family's sealed held-out test "
                "distribution under its sealed seed itself (HELDOUT_SEED; taskvar eval --test "
                "heldout draws each bundle's own episodes from it), the same episodes for every "
                "method and seed; gap_closed against these references"
            ),
        }
    write_csv(out / CSV_NAME, csv_rows(metrics), csv_fields(metrics))
    write_json(out / METRICS_NAME, metrics)
    if plots:  # else ``taskvar plot DIR`` draws it from the folder
        plot_results(out)
    print(format_table(metrics))
    return metrics


__all__ = [  # the registry's entry points (experiments/registry.py): run, loader, config, plot
    "default_config_path",
    "load_scale_config",
    "plot_results",
    "scale",
]
