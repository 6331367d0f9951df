"""Scaled-up grids (docs/scale.md): training time and final performance of the four methods against
grid size and the number of parallel environments.

For each case (a family config) and ``num_envs`` value (a cell), :func:`scale` trains every head on
the same frame budget, evaluates averaging (§3.1), options (§3.2), interruption (Algorithm 1) and
hierarchy (Algorithm 2) on paired test episodes, and plays the references on the same episodes:
``gap_closed = (R - R_random) / (R_oracle - R_random)``. Held-out instances, baselines and seeds:
docs/scale.md. Writes ``config.yaml``, ``cells/<case>-n<N>/``, ``scale.csv``, ``metrics.json`` and
``scale.png``.
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
    """Load ``configs/scale.yaml`` strictly, apply ``quick_overrides`` with ``quick``, then
    ``key=value`` overrides; every case's family config is loaded to fail early.

    ``path`` may also be one family's config: the one case of the default scale config
    (docs/scale.md).
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
    """Run every (case, num_envs) cell into ``out_dir`` (a staged
    :class:`~taskvar_torch.run_folder.ResultsFolder`; ``overwrite`` replaces results already there),
    print the table; returns ``metrics.json``'s dict.
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
