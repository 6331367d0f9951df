"""Wargus Figure 4: the lifelong protocol (paper §3.5.1-3.5.3;
docs/wargus-fig4.md#protocol-paper-351).

:func:`wargus_fig4` runs R repetitions (seed ``cfg.seed + rep``, no prior knowledge) of T trials
(learning, nominal test, held-out test), batched
(:func:`~.fig4_repetition.run_repetitions_batched`) or split over ``workers`` processes, and
writes the results folder; this module re-exports the public names of :mod:`.fig4_agent`,
:mod:`.fig4_trial`, :mod:`.fig4_repetition`, :mod:`.fig4_metrics`, :mod:`.fig4_report`,
:mod:`taskvar_torch.controllers.side_by_side` and :mod:`taskvar_torch.heads.snapshots`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as mp

from taskvar_torch.config import Config, save_config_yaml
from taskvar_torch.contract import FAMILIES
from taskvar_torch.experiments.results import write_csv, write_json
from taskvar_torch.families.wargus.family import section
from taskvar_torch.families.wargus.fig4_metrics import (
    EXPERIMENT,
    summarise,
)
from taskvar_torch.families.wargus.fig4_recurrent import run_recurrent_batch
from taskvar_torch.families.wargus.fig4_repetition import (
    BASELINES_CSV,
    BASELINES_CSV_FIELDS,
    HELDOUT_CSV,
    HELDOUT_KEYS,
    PHASES,
    _add_baseline,
    heldout_summary,
    run_repetitions_batched,
)
from taskvar_torch.families.wargus.fig4_report import (
    CSV_FIELDS,
    csv_rows,
    format_table,
    plot_results,
)
from taskvar_torch.families.wargus.fig4_trial import (
    repetition_seed,
)
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import ResultsFolder


def default_config_path() -> Path:
    """``configs/wargus.yaml`` of the repository (or of the working directory)."""
    here = Path(__file__).resolve().parents[3] / "configs" / "wargus.yaml"
    return here if here.is_file() else Path("configs") / "wargus.yaml"


def repetition_batches(reps: int, workers: int) -> list[list[int]]:
    """The repetitions ``0 .. reps - 1`` in ``min(workers, reps)`` contiguous batches of sizes
    differing by at most one (each batch one process, one batched loop)."""
    w = max(1, min(workers, reps))
    size, extra = divmod(reps, w)
    out, first = [], 0
    for i in range(w):
        n = size + (1 if i < extra else 0)
        out.append(list(range(first, first + n)))
        first += n
    return out


RunBatch = Callable[..., list[dict[str, Any]]]
"""``(cfg, reps, out_dir, on_trial) -> results``: :func:`run_repetitions_batched`, or a baseline's
(``fig4_recurrent.run_recurrent_batch``)."""


def _worker(
    cfg: Config, reps: list[int], out_dir: str, threads: int, queue: Any, run_batch: RunBatch
) -> None:
    """Process entry: one batch of repetitions, progress and results through ``queue``."""
    torch.set_num_threads(threads)
    try:
        done = run_batch(cfg, reps, out_dir, lambda r, t: queue.put(("trial", r, None)))
        for rep, result in zip(reps, done):
            queue.put(("done", rep, result))
    except BaseException as e:  # report, so the parent does not wait forever
        queue.put(("error", reps[0], f"{type(e).__name__}: {e}"))


def run_repetitions(
    cfg: Config,
    out_dir: str | os.PathLike,
    workers: int = 1,
    progress: bool = True,
    run_batch: RunBatch = run_repetitions_batched,
    desc: str = EXPERIMENT,
) -> list[dict[str, Any]]:
    """Every repetition through ``run_batch``, here (``workers = 1``) or as ``workers`` batches in
    spawned processes; the same numbers either way.
    """
    reps = cfg.experiment.runs
    bar = progress_bar(
        total=reps * cfg.experiment.trials, disable=not progress, desc=desc, unit="trial"
    )
    results: dict[int, dict[str, Any]] = {}
    batches = repetition_batches(reps, workers)
    if len(batches) == 1:
        done = run_batch(cfg, batches[0], out_dir, lambda r, t: bar.update(1))
        results = dict(zip(batches[0], done))
    else:
        ctx = mp.get_context("spawn")
        queue = ctx.Queue()
        threads = max(1, torch.get_num_threads() // len(batches))
        procs = [
            ctx.Process(
                target=_worker,
                args=(cfg, b, str(out_dir), threads, queue, run_batch),
                daemon=True,
            )
            for b in batches
        ]
        try:
            for proc in procs:
                proc.start()
            while len(results) < reps:
                kind, rep, payload = queue.get()
                if kind == "trial":
                    bar.update(1)
                elif kind == "error":
                    raise RuntimeError(f"repetition {rep} failed: {payload}")
                else:
                    results[rep] = payload
            for proc in procs:
                proc.join()
        finally:  # an error or Ctrl-C here stops the other batches too
            for proc in procs:
                if proc.is_alive():
                    proc.terminate()
    bar.close()
    return [results[r] for r in range(reps)]


# --------------------------------------------------------------------------------------------
# the experiment


def wargus_fig4(
    cfg: Config,
    out_dir: str | os.PathLike,
    workers: int = 1,
    progress: bool = True,
    plots: bool = True,
    overwrite: bool = False,
    staged: bool = True,
) -> dict[str, Any]:
    """Run the lifelong protocol, write ``out_dir`` (a
    :class:`~taskvar_torch.run_folder.ResultsFolder`), print the table. ``plots=False`` skips
    ``fig4.png``; ``overwrite`` replaces results (otherwise refused); ``staged=False`` writes into
    ``out_dir`` directly (a sweep's point).
    """
    FAMILIES["wargus"].require(cfg, "wargus-fig4")
    if cfg.train.eval_ema_tau is not None:
        raise ValueError(
            f"train.eval_ema_tau={cfg.train.eval_ema_tau}: wargus-fig4 tests the live heads after "
            "every trial (paper §3.5.1), it has no averaged weights to test; set it to null"
        )
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if not staged:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        return _wargus_fig4(cfg, out, workers, progress, plots)
    with ResultsFolder(out_dir, overwrite, "taskvar experiment wargus-fig4") as staging:
        return _wargus_fig4(cfg, staging, workers, progress, plots)


def _wargus_fig4(
    cfg: Config, out: Path, workers: int, progress: bool, plots: bool
) -> dict[str, Any]:
    """:func:`wargus_fig4` writing into the folder ``out``."""
    save_config_yaml(cfg, out / "config.yaml")

    start = time.perf_counter()
    results = run_repetitions(cfg, out, workers=workers, progress=progress)
    wall = time.perf_counter() - start
    baselines = {}  # the baselines' agents after the paper's (their own streams: fig4_recurrent)
    for name in cfg.experiment.baselines:
        tick = time.perf_counter()
        run_batch = {"recurrent": run_recurrent_batch}[name]
        done = run_repetitions(cfg, out, workers, progress, run_batch=run_batch, desc=name)
        baselines[name] = (done, time.perf_counter() - tick)

    items = np.stack([r["items"] for r in results])  # (R, T, M)
    inter = np.stack([r["interruptions"] for r in results])  # (R, T, M)
    control = np.stack([r["control_steps"] for r in results])  # (R, T, O)
    lost = np.stack([r["item_lost"] for r in results])  # (R, T, M)
    write_csv(out / "per_trial.csv", csv_rows(items, inter), CSV_FIELDS)
    metrics = summarise(
        items, inter, control, results[0]["option_names"], results[0]["option_depths"], lost
    )
    held = {k: np.stack([r[f"heldout_{k}"] for r in results]) for k in HELDOUT_KEYS}
    write_csv(out / HELDOUT_CSV, csv_rows(held["items"], held["interruptions"]), CSV_FIELDS)
    metrics["heldout"] = heldout_summary(held, results[0])
    metrics["protocol"] = {
        "repetitions": cfg.experiment.runs,
        "trials": cfg.experiment.trials,
        "learning_episodes_per_trial": cfg.experiment.learning_episodes_per_trial,
        "test_episodes_per_trial": cfg.experiment.test_episodes_per_trial,
        "seeds": [repetition_seed(cfg, r) for r in range(cfg.experiment.runs)],
        "tau": cfg.train.robustness_tau,
        "threshold": cfg.train.robustness_threshold,
        "keep_share": cfg.train.robustness_keep_share,
        "grid": section(cfg).size,
        "horizon": section(cfg).horizon,
        "workers": workers,
    }
    metrics["timing"] = {
        "wall_seconds": wall,
        "seconds_per_trial": wall / max(cfg.experiment.runs * cfg.experiment.trials, 1),
        "repetition_seconds": [r["seconds"] for r in results],
        "frames_per_repetition": [int(r["frames"].sum()) for r in results],
        "updates_per_repetition": [int(r["updates"][-1]) for r in results],
        # where a trial's CPU goes, per phase, over every repetition and trial
        "cpu_seconds_per_trial": {
            phase: sum(r["cpu_seconds"][phase] for r in results)
            / max(cfg.experiment.runs * cfg.experiment.trials, 1)
            for phase in PHASES
        },
    }
    learn = np.stack([r["learn_items"] for r in results])  # (R, T)
    metrics["learning_items"] = {
        "curve_mean": learn.mean(0).tolist(),
        "curve_per_rep": learn.tolist(),
    }
    for name, (done, seconds) in baselines.items():
        _add_baseline(metrics, name, done, seconds)
    if baselines:
        rows = [
            {"rep": r, "trial": t + 1, "method": name, "items": float(a), "heldout_items": float(b)}
            for name, (done, _) in baselines.items()
            for r, one in enumerate(done)
            for t, (a, b) in enumerate(zip(one["items"], one["heldout_items"]))
        ]
        write_csv(out / BASELINES_CSV, rows, BASELINES_CSV_FIELDS)
    write_json(out / "metrics.json", metrics)
    if plots:  # else ``taskvar plot DIR`` draws them from the folder
        plot_results(out)
    print(format_table(metrics))
    return metrics


__all__ = [  # the protocol and the registry's entry points (experiments/registry.py)
    "default_config_path",
    "plot_results",
    "repetition_batches",
    "run_repetitions",
    "wargus_fig4",
]
