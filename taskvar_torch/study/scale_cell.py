"""One cell of the scale experiment (docs/scale.md): every head trained, each seed's bundle
evaluated, aggregated over seeds, the baselines and the held-out block.
"""

from __future__ import annotations

import resource
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import (
    METHODS,
    Config,
)
from taskvar_torch.contract import family
from taskvar_torch.factory import load_heads
from taskvar_torch.heads.recurrent import (
    BaselineController,
    load_baseline,
)
from taskvar_torch.study.scale_config import ScaleCase, ScaleConfig, case_config
from taskvar_torch.study.scale_eval import (
    HELDOUT_TEST,
    evaluate,
    family_figure,
    gap_closed,
    grid_side,
    heldout_test,
    isolated_rng,
    references,
)
from taskvar_torch.training import train
from taskvar_torch.training.baselines import train_baseline
from taskvar_torch.training.run_state import HEADS_SNAPSHOTS, seed_config

SEED_CI_REPS = 2000
"""Bootstrap replications of :func:`over_seeds`' 95% CIs (rliable's default; ~0.5-2 s a method)."""


# --------------------------------------------------------------------------------------------
# the experiment


def run_cell(
    cfg: ScaleConfig,
    case: ScaleCase,
    num_envs: int,
    out: Path,
    refs: dict[str, Any],
    overwrite: bool = False,
    heldout_refs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train one (case, num_envs) cell with the real trainer, time it, evaluate every method.

    With ``cfg.seeds > 1`` every seed's bundle plays the same test episodes (``per_seed``,
    ``over_seeds``); ``heldout_refs`` adds :func:`heldout_block`, ``cfg.baselines``
    :func:`baseline_phase`.
    """

    ccfg = case_config(cfg, case, num_envs)
    ecfg = seed_config(ccfg, 0)  # seed `seed` as one run: the test episodes of every seed
    cell_dir = out / "cells" / f"{case.name}-n{num_envs}"
    # final.pt is deleted after evaluation unless kept: then it needs no replay buffer (~1.3 GB)
    result = train(
        ccfg, cell_dir, progress=False, overwrite=overwrite, keep_replay=cfg.keep_checkpoints
    )
    finals = [Path(p) for p in result.get("seeds", [result["final"]])]
    seed_heads = [load_heads(p, device=ccfg.device)[0] for p in finals]
    if not cfg.keep_checkpoints:
        for p in {Path(result["final"]), *finals}:
            p.unlink(missing_ok=True)
    t0 = time.perf_counter()
    rand = refs["random"]["mean_return"]
    orc = refs["oracle_averaging"]["mean_return"] if refs["oracle_averaging"] else None
    per_seed = []
    for heads in seed_heads:
        methods = {
            m: evaluate(ecfg, m, cfg.eval_episodes, cfg.eval_batch_size, heads) for m in METHODS
        }
        for r in methods.values():
            if r is not None:
                r["gap_closed"] = gap_closed(r["mean_return"], rand, orc)
        per_seed.append(methods)
    methods, heads = per_seed[0], seed_heads[0]
    curve = learning_curve(cfg, ecfg, finals[0].parent, rand, orc)
    for other in finals[1:]:  # seed 0's curve only (each point evaluates every method)
        if not cfg.keep_checkpoints:
            for path in (other.parent / HEADS_SNAPSHOTS).glob("heads_*.pt"):
                path.unlink(missing_ok=True)
    curve.append(
        {
            "frames": int(result["frames"]),
            "updates": int(result["updates"]),
            "seconds": float(result["seconds"]),
            "methods": {m: _curve_point(r) for m, r in methods.items()},
        }
    )
    report = None
    if cfg.head_report and family(ccfg).head_report is not None:
        report = family(ccfg).head_report(ecfg, heads, with_max_value=cfg.head_report_max_value)
    secs = float(result["seconds"])
    cell = {
        **peak_memory(ccfg.device),
        "case": case.name,
        "family": ccfg.family,
        "grid_side": grid_side(ccfg),
        "cells": family_figure(ccfg, "cells"),
        "num_envs": int(num_envs),
        "frames": int(result["frames"]),
        "updates": int(result["updates"]),
        "frames_per_batch": ccfg.train.frames_per_batch,
        "updates_per_batch": ccfg.train.updates_per_batch,
        "hidden": list(ccfg.heads.hidden),
        "obs_encoding": family_figure(ccfg, "observation"),
        "train_seconds": secs,
        "frames_per_second": result["frames"] / secs if secs > 0 else None,
        "eval_seconds": time.perf_counter() - t0,
        "methods": methods,
        "curve": curve,
        "heads": report,
    }
    if cfg.seeds > 1:  # new keys only: with one seed the cell is what it always was
        seeds = [ccfg.seed + k for k in range(cfg.seeds)]
        cell["seeds"] = seeds
        cell["frames_per_second_all_seeds"] = (
            result["frames"] * cfg.seeds / secs if secs > 0 else None
        )
        cell["per_seed"] = [{"seed": s, "methods": m} for s, m in zip(seeds, per_seed)]
        cell["over_seeds"] = over_seeds(per_seed, rand, orc)
    seed_baselines: list[dict[str, BaselineController]] = []
    if cfg.baselines:  # new keys only, after the methods' own (docs/scale.md#baselines)
        folders = [p.parent for p in finals]
        seed_baselines = baseline_phase(cfg, ccfg, ecfg, folders, cell, per_seed, rand, orc)
    if heldout_refs is not None and cfg.heldout_count() > 0:  # new key only, after the rest
        cell["heldout"] = heldout_block(cfg, ecfg, seed_heads, heldout_refs, seed_baselines)
    return cell


def baseline_phase(
    cfg: ScaleConfig,
    ccfg: Config,
    ecfg: Config,
    folders: Sequence[Path],
    cell: dict[str, Any],
    per_seed: Sequence[dict[str, Any]],
    random_ret: float,
    oracle_ret: float | None,
) -> list[dict[str, BaselineController]]:
    """Train and score a cell's baselines (docs/scale.md#baselines); returns each seed's greedy
    controllers by name.

    Each seed's baselines train on the cell's config (the heads' budget) into its bundle folder, as
    ``taskvar train-baselines`` does, and play the methods' test episodes; they become new entries
    of ``methods``, ``per_seed`` and ``over_seeds``, with ``baseline_training``,
    ``baseline_train_seconds`` and ``baseline_eval_seconds``. Runs under :func:`isolated_rng`.
    """
    controllers: list[dict[str, BaselineController]] = []
    training = []
    for k, folder in enumerate(folders):
        scfg = seed_config(ccfg, k)
        ctrls = {}
        for b in cfg.baselines:
            with isolated_rng(ccfg.device):  # loading draws too: the network's initial weights
                r = train_baseline(scfg, b, folder)
                ctrls[b], _ = load_baseline(r["path"], device=ccfg.device)
            if not cfg.keep_checkpoints:
                Path(r["path"]).unlink(missing_ok=True)
            last = r["mean_train_return"]
            training.append(
                {
                    "seed": scfg.seed,
                    "method": b,
                    "frames": int(r["frames"]),
                    "updates": int(r["updates"]),
                    "train_seconds": float(r["seconds"]),
                    "mean_train_return": None if last != last else float(last),  # NaN: none ended
                    "with_heads": False,
                }
            )
        controllers.append(ctrls)
    t0 = time.perf_counter()
    with isolated_rng(ecfg.device):
        for methods, ctrls in zip(per_seed, controllers):
            for b, ctrl in ctrls.items():
                r = evaluate(ecfg, b, cfg.eval_episodes, cfg.eval_batch_size, ctrl)
                r["gap_closed"] = gap_closed(r["mean_return"], random_ret, oracle_ret)
                methods[b] = r
        if cfg.seeds > 1:
            cell["over_seeds"].update(over_seeds(per_seed, random_ret, oracle_ret, cfg.baselines))
    cell["baseline_training"] = training
    cell["baseline_train_seconds"] = sum(t["train_seconds"] for t in training)
    cell["baseline_eval_seconds"] = time.perf_counter() - t0
    return controllers


def heldout_references(cfg: ScaleConfig, ccfg: Config) -> dict[str, Any] | None:
    """A case's references on :func:`heldout_test`'s episodes, with the test's name, seed and
    description; ``None`` without a held-out test. Drawn under :func:`isolated_rng`.
    """
    test = heldout_test(ccfg)
    if test is None:
        return None
    n = cfg.heldout_count()
    with isolated_rng(ccfg.device):
        refs = references(test.cfg, n, min(n, cfg.eval_batch_size), test)
    return {
        "test": HELDOUT_TEST,
        "description": test.description,
        "seed": test.seed,
        "episodes": n,
        **refs,
    }


def heldout_block(
    cfg: ScaleConfig,
    ecfg: Config,
    seed_heads: Sequence[Any],
    refs: dict[str, Any],
    seed_baselines: Sequence[dict[str, BaselineController]] = (),
) -> dict[str, Any]:
    """A cell's ``heldout``: every method (and ``seed_baselines``) on the held-out episodes, shaped
    like the cell's own keys (docs/scale.md#held-out-instances). Runs under :func:`isolated_rng`.
    """
    t0 = time.perf_counter()
    test = heldout_test(ecfg)
    n = cfg.heldout_count()
    rand = refs["random"]["mean_return"]
    orc = refs["oracle_averaging"]["mean_return"] if refs["oracle_averaging"] else None
    per_seed = []
    with isolated_rng(ecfg.device):
        for heads in seed_heads:
            methods = {
                m: evaluate(ecfg, m, n, min(n, cfg.eval_batch_size), heads, test) for m in METHODS
            }
            for r in methods.values():
                if r is not None:
                    r["gap_closed"] = gap_closed(r["mean_return"], rand, orc)
            per_seed.append(methods)
        block: dict[str, Any] = {"methods": per_seed[0]}
        if cfg.seeds > 1:
            seeds = [ecfg.seed + k for k in range(cfg.seeds)]
            block["per_seed"] = [{"seed": s, "methods": m} for s, m in zip(seeds, per_seed)]
            block["over_seeds"] = over_seeds(per_seed, rand, orc)
        for methods, ctrls in zip(per_seed, seed_baselines):  # after the methods': new entries
            for b, ctrl in ctrls.items():
                r = evaluate(ecfg, b, n, min(n, cfg.eval_batch_size), ctrl, test)
                r["gap_closed"] = gap_closed(r["mean_return"], rand, orc)
                methods[b] = r
        if cfg.seeds > 1 and seed_baselines:
            block["over_seeds"].update(over_seeds(per_seed, rand, orc, list(seed_baselines[0])))
    block["seconds"] = time.perf_counter() - t0
    return block


def over_seeds(
    per_seed: Sequence[dict[str, Any]],
    random_ret: float,
    oracle_ret: float | None,
    methods: Sequence[str] = METHODS,
) -> dict[str, dict[str, Any] | None]:
    """Each method's per-seed mean test return aggregated with
    :func:`taskvar_torch.study.aggregate.interval_estimates`: ``mean_return``, ``mean_ci95``, the
    IQM, ``returns`` and the gap closed; ``None`` where the method does not apply.
    """
    from taskvar_torch.study.aggregate import interval_estimates

    scores = {
        m: [[s[m]["mean_return"]] for s in per_seed]
        for m in methods
        if all(s.get(m) is not None for s in per_seed)
    }
    est = interval_estimates(scores, reps=SEED_CI_REPS) if scores else {}
    out: dict[str, dict[str, Any] | None] = {}
    for m in methods:
        if m not in est:
            out[m] = None
            continue
        e = est[m]
        gaps = [gap_closed(x, random_ret, oracle_ret) for x in e["mean_ci95"]]
        out[m] = {
            "seeds": e["runs"],
            "returns": [row[0] for row in scores[m]],
            "mean_return": e["mean"],
            "mean_ci95": e["mean_ci95"],
            "iqm_return": e["iqm"],
            "iqm_ci95": e["iqm_ci95"],
            "gap_closed": gap_closed(e["mean"], random_ret, oracle_ret),
            "gap_closed_ci95": None if gaps[0] is None else sorted(gaps),
        }
    return out


def peak_memory(device: str | torch.device) -> dict[str, float | None]:
    """``peak_rss_mb``: this process's peak resident memory so far (a high-water mark: with
    several cells in one process, the largest cell run so far; Linux and macOS), and on CUDA
    ``peak_cuda_mb``, the peak of tensors allocated on the device so far (else ``None``)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    rss_mb = rss / 2**20 if sys.platform == "darwin" else rss / 2**10
    dev = torch.device(device)
    cuda = torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else None
    return {"peak_rss_mb": float(rss_mb), "peak_cuda_mb": cuda}


def _curve_point(r: dict[str, Any] | None) -> dict[str, Any] | None:
    return None if r is None else {k: r.get(k) for k in ("mean_return", "ci95", "gap_closed")}


def learning_curve(
    cfg: ScaleConfig, ccfg: Config, cell_dir: Path, random_ret: float, oracle_ret: float | None
) -> list[dict[str, Any]]:
    """Every method on each heads snapshot of a cell (``train.heads_every``), on the first
    ``curve_episodes`` test episodes; the snapshots are removed once read."""
    points = []
    snapshots = sorted((cell_dir / HEADS_SNAPSHOTS).glob("heads_*.pt"))
    n = min(cfg.curve_episodes, cfg.eval_episodes)
    for path in snapshots:
        heads, _ = load_heads(path, device=ccfg.device)
        counters = load_checkpoint(path)["counters"]
        methods = {}
        for m in METHODS:
            r = evaluate(ccfg, m, n, min(n, cfg.eval_batch_size), heads)
            if r is not None:
                r["gap_closed"] = gap_closed(r["mean_return"], random_ret, oracle_ret)
            methods[m] = _curve_point(r)
        points.append(
            {
                "frames": int(counters["frames"]),
                "updates": int(counters["updates"]),
                "seconds": float(counters["seconds"]),
                "methods": methods,
            }
        )
    if not cfg.keep_checkpoints:
        for path in snapshots:
            path.unlink(missing_ok=True)
    return points


__all__ = [
    "SEED_CI_REPS",
    "baseline_phase",
    "heldout_block",
    "heldout_references",
    "learning_curve",
    "over_seeds",
    "peak_memory",
    "run_cell",
]
