"""What a sweep's workers run: one point (:func:`run_point`, as ``taskvar experiment``) or a seed
batch trained as one ``train.seeds = k`` run (:func:`run_batch`; docs/seeds.md); :func:`plan_jobs`
turns the points into these jobs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import json
import os
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from taskvar_torch.config import Config, apply_overrides, config_to_dict
from taskvar_torch.contract import family
from taskvar_torch.experiments.results import write_json
from taskvar_torch.study.sweep_grid import SweepPoint, point_name
from taskvar_torch.training import train
from taskvar_torch.training.learning import TrainingDiverged

POINT_LOG = "output.txt"
BATCHES = "batches"
"""``OUT/batches/<name>/``: the training run of a seed batch (``train.seeds = k``)."""


# --------------------------------------------------------------------------------------------
# one point (the same function as ``taskvar experiment``)


def run_point(
    cfg: Config,
    out_dir: str,
    quick: bool = False,
    plots: bool = True,
    overwrite: bool = False,
    checkpoint: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """Run ``cfg``'s family experiment into ``out_dir`` (its table in ``output.txt``);
    ``checkpoint`` evaluates that bundle instead of training. Returns ``{"metrics", "seconds"}``, or
    ``{"error", "seconds"}`` for a diverged run.
    """

    torch.set_num_threads(1)  # one core per point (the heads are small MLPs)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if checkpoint is None and (out / "train").is_symlink():
        (out / "train").unlink()  # a killed batched attempt's link: this point now trains alone
    t0 = time.perf_counter()
    exp = family(cfg).experiment
    options = {} if checkpoint is None else {"checkpoint": checkpoint}
    if exp.takes("quick"):
        options["quick"] = quick  # elsewhere --quick only picked the quick overrides
    if exp.takes("workers"):
        options["workers"] = 1  # one process per point
    with open(out / POINT_LOG, "w") as log, contextlib.redirect_stdout(log):
        try:
            metrics = exp.call(
                cfg,
                out,
                progress=False,
                plots=plots,
                overwrite=overwrite,
                staged=False,  # the sweep holds its folder (sweep())
                **options,
            )
        except TrainingDiverged as e:
            print(f"error: {e}")
            return {"error": f"TrainingDiverged: {e}", "seconds": time.perf_counter() - t0}
    return {"metrics": metrics, "seconds": time.perf_counter() - t0}


# --------------------------------------------------------------------------------------------
# seed batches: points that differ only in the seed, trained as one ``train.seeds = k`` run


@dataclass(frozen=True)
class Job:
    """What one worker runs: sweep points (indices), their configs and folders; with ``batch`` (a
    folder) the points are consecutive seeds of one config, trained once (:func:`run_batch`)."""

    points: tuple[int, ...]
    cfgs: tuple[Config, ...] = field(repr=False)
    outs: tuple[str, ...]
    batch: str | None = None


def batch_refusal(cfg: Config) -> str | None:
    """Why points of ``cfg`` cannot be trained as one seed batch (``None``: they can): the
    family's experiment must evaluate a given bundle (``checkpoint``) and the batched trainer
    must take the config (``train.seeds = 1`` now, one collector process, an MLP trunk)."""
    exp = family(cfg).experiment
    if "checkpoint" not in inspect.signature(exp.function("run")).parameters:
        return f"{exp.name} trains in its own loop, not with taskvar train"
    if cfg.train.seeds != 1:
        return f"each point is already a batch (train.seeds={cfg.train.seeds})"
    try:
        apply_overrides(cfg, ["train.seeds=2"])
    except ValueError as e:
        return str(e).strip().splitlines()[0]
    return None


def seed_batches(
    points: Sequence[SweepPoint], cfgs: Sequence[Config], todo: Sequence[int]
) -> tuple[list[list[int]], list[str]]:
    """The seed batches among ``todo``: lists of >= 2 point indices equal but for consecutive seeds,
    and a note per group of such points not wholly batched.
    """
    groups: dict[str, list[int]] = {}
    for i in todo:
        key = json.dumps(config_to_dict(dataclasses.replace(cfgs[i], seed=0)), sort_keys=True)
        groups.setdefault(key, []).append(i)
    batches, notes = [], []
    for idx in groups.values():
        if len(idx) < 2:
            continue
        names = ", ".join(points[i].name for i in idx)
        why = batch_refusal(cfgs[idx[0]])
        if why is not None:
            notes.append(f"seed batches: points {names} run one by one: {why}")
            continue
        runs: list[list[int]] = []
        for i in sorted(idx, key=lambda i: cfgs[i].seed):
            if runs and cfgs[i].seed == cfgs[runs[-1][-1]].seed + 1:
                runs[-1].append(i)
            else:
                runs.append([i])
        batches += [r for r in runs if len(r) > 1]
        if len(runs) > 1:
            seeds = ", ".join(str(cfgs[i].seed) for i in sorted(idx, key=lambda i: cfgs[i].seed))
            notes.append(
                f"seed batches: seeds {seeds} (points {names}) are not consecutive: "
                f"{sum(len(r) > 1 for r in runs)} batch(es) of consecutive seeds, "
                f"{sum(len(r) == 1 for r in runs)} point(s) trained alone"
            )
    return batches, notes


def batch_name(points: Sequence[SweepPoint], cfgs: Sequence[Config], idx: Sequence[int]) -> str:
    """Folder name of a batch: its first point's swept values with ``seed=<first>-<last>``."""
    values = {k: v for k, v in points[idx[0]].values.items() if k != "seed"}
    values["seed"] = f"{cfgs[idx[0]].seed}-{cfgs[idx[-1]].seed}"
    return point_name(values)


def plan_jobs(
    points: Sequence[SweepPoint],
    cfgs: Sequence[Config],
    todo: Sequence[int],
    out: Path,
    batch_seeds: bool = True,
) -> tuple[list[Job], list[str]]:
    """The jobs running the points ``todo`` (in the order of their first point): a seed batch
    each (with ``batch_seeds``, :func:`seed_batches`), one job per other point; and the notes."""
    batches, notes = seed_batches(points, cfgs, todo) if batch_seeds else ([], [])
    batched = {i for b in batches for i in b}
    jobs = [
        Job(tuple(b), tuple(cfgs[i] for i in b), tuple(str(out / points[i].name) for i in b),
            str(out / BATCHES / batch_name(points, cfgs, b)))
        for b in batches
    ] + [
        Job((i,), (cfgs[i],), (str(out / points[i].name),)) for i in todo if i not in batched
    ]  # fmt: skip
    return sorted(jobs, key=lambda j: min(j.points)), notes


def run_job(
    job: Job, quick: bool = False, plots: bool = True, overwrite: bool = False
) -> list[dict[str, Any]]:
    """Run one job: its one point (:func:`run_point`) or its seed batch (:func:`run_batch`);
    one result per point."""
    if job.batch is None:
        return [run_point(c, o, quick, plots, overwrite) for c, o in zip(job.cfgs, job.outs)]
    return run_batch(job.cfgs, job.outs, job.batch, quick, plots, overwrite)


def run_batch(
    cfgs: Sequence[Config],
    outs: Sequence[str],
    batch_dir: str,
    quick: bool = False,
    plots: bool = True,
    overwrite: bool = False,
) -> list[dict[str, Any]]:
    """Train the points ``cfgs`` as one ``train.seeds = k`` run in ``batch_dir``, then run each
    point's experiment on its seed's bundle (``outs[i]/train`` a relative symlink); each
    ``metrics.json`` gains ``train_batch`` and its share of the training time.
    """
    torch.set_num_threads(1)
    n, batch = len(cfgs), Path(batch_dir)
    bcfg = apply_overrides(cfgs[0], [f"train.seeds={n}"])
    batch.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(batch / POINT_LOG, "w") as log, contextlib.redirect_stdout(log):
        try:
            result = train(bcfg, batch, progress=False, overwrite=overwrite)
        except TrainingDiverged as e:
            print(f"error: {e}")
            error = {"error": f"TrainingDiverged: {e}", "seconds": (time.perf_counter() - t0) / n}
            for out in outs:
                Path(out).mkdir(parents=True, exist_ok=True)
                (Path(out) / POINT_LOG).write_text(f"error: {e} (seed batch {batch})\n")
            return [dict(error) for _ in outs]
    share, wall_share = float(result["seconds"]) / n, (time.perf_counter() - t0) / n
    results = []
    for k, (cfg, out, bundle) in enumerate(zip(cfgs, outs, result["seeds"])):
        point = Path(out)
        point.mkdir(parents=True, exist_ok=True)
        link = point / "train"
        if link.is_symlink() or link.is_file():
            link.unlink()
        elif link.is_dir():  # an unbatched run of this point (--overwrite or --resume)
            shutil.rmtree(link)
        link.symlink_to(os.path.relpath(Path(bundle).parent, point), target_is_directory=True)
        r = run_point(cfg, out, quick, plots, overwrite, checkpoint=link / "final.pt")
        if "metrics" in r:
            m = r["metrics"]
            m["train_seconds"] = share
            m["wall_seconds"] = float(m.get("wall_seconds", 0.0)) + wall_share
            m["train_batch"] = {
                "folder": os.path.relpath(batch, point),
                "seeds": n,
                "seed_index": k,
            }
            write_json(point / "metrics.json", m)
        r["seconds"] += wall_share
        results.append(r)
    return results


__all__ = [
    "BATCHES",
    "POINT_LOG",
    "Job",
    "batch_name",
    "batch_refusal",
    "plan_jobs",
    "run_batch",
    "run_job",
    "run_point",
    "seed_batches",
]
