"""Sweeps: one experiment per point of a grid of config overrides, run locally or on Ray
(docs/sweeps.md).

The grid is :mod:`taskvar_torch.study.sweep_grid`, what a worker runs
:mod:`taskvar_torch.study.sweep_jobs`; this module runs the jobs on a backend (:data:`BACKENDS`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from taskvar_torch.config import Config
from taskvar_torch.contract import family
from taskvar_torch.experiments.results import write_csv, write_json
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import ResultsFolder, check_out_path, check_output_folder
from taskvar_torch.study.sweep_grid import (
    SweepPoint,
    completed_points,
    expand_points,
    format_summary,
    load_point_configs,
    summary_rows,
)
from taskvar_torch.study.sweep_jobs import BATCHES, Job, plan_jobs, run_job

BACKENDS = ("local", "ray")
"""Config family -> the experiment each sweep point runs (as ``taskvar experiment NAME``)."""
RAY_MISSING = 'taskvar sweep --backend ray needs Ray: pip install "taskvar-torch[distributed]"'
SUMMARY_CSV, SUMMARY_JSON = "summary.csv", "summary.json"
RAY_RETRIES = 1
"""Ray backend: a point whose worker process dies is run again this many times, then recorded as
failed (its summary row's ``error``; the sweep goes on)."""


# --------------------------------------------------------------------------------------------
# backends


def _run_local(
    jobs: list[Job], quick: bool, progress: bool, plots: bool, overwrite: bool
) -> list[dict[str, Any]]:
    results = []
    with progress_bar(
        total=sum(len(j.points) for j in jobs), disable=not progress, desc="sweep", unit="point"
    ) as bar:
        for job in jobs:
            results += run_job(job, quick, plots, overwrite)
            bar.update(len(job.points))
    return results


def _run_ray(
    jobs: list[Job],
    quick: bool,
    progress: bool,
    address: str | None,
    workers: int | None,
    plots: bool,
) -> list[dict[str, Any]]:
    try:
        import ray  # optional dependency (the distributed extra): imported only on the ray backend
    except ImportError:
        raise ValueError(RAY_MISSING) from None
    started = not ray.is_initialized()  # an already running Ray (a notebook, a test) is reused
    if started:
        if address is None:  # "local": a new Ray, never a cluster found in RAY_ADDRESS
            ray.init(
                address="local",
                num_cpus=workers or os.cpu_count() or 1,
                include_dashboard=False,
                log_to_driver=False,
            )
        else:  # a cluster: "auto", "HOST:6379", or "ray://HOST:10001" (Ray Client)
            try:
                ray.init(address=address, log_to_driver=False)
            except ConnectionError as e:
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise ValueError(f"--address {address!r}: {first}") from None
    try:
        # A task whose worker dies (killed, out of memory, node lost) is retried RAY_RETRIES
        # times; the sweep refused non-empty point folders up front (or was told to overwrite or
        # resume), so what a retry finds in its folder is its own killed attempt: overwrite.
        task = ray.remote(num_cpus=1, max_retries=RAY_RETRIES)(run_job)
        refs = [task.remote(job, quick, plots, True) for job in jobs]
        size = {ref: len(job.points) for ref, job in zip(refs, jobs)}
        pending = list(refs)
        with progress_bar(
            total=sum(size.values()), disable=not progress, desc="sweep", unit="point"
        ) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                bar.update(sum(size[r] for r in done))
        results = []
        for ref, job in zip(refs, jobs):
            r = _ray_result(ray, ref)  # a crashed job: the same failed row for each of its points
            results += r if isinstance(r, list) else [dict(r) for _ in job.points]
        return results
    finally:
        if started:
            ray.shutdown()


def _ray_result(ray: Any, ref: Any) -> list[dict[str, Any]] | dict[str, Any]:
    """A task's results (one per point); a task whose worker died on every try is a failed point
    (its error: one dict)."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError:  # the point itself raised: as on the local backend
        raise
    except ray.exceptions.RayError as e:  # WorkerCrashedError, OutOfMemoryError, NodeDiedError...
        text = str(e).strip()
        first = text.splitlines()[0] if text else ""
        return {"error": f"{type(e).__name__}: {first}".rstrip(": "), "seconds": None}


def sweep(
    config: str | os.PathLike,
    items: Sequence[str],
    out_dir: str | os.PathLike,
    backend: str = "local",
    quick: bool = False,
    address: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    plots: bool = True,
    overwrite: bool = False,
    resume: bool = False,
    batch_seeds: bool = True,
) -> list[dict[str, Any]]:
    """Run every point of the sweep, write ``summary.csv`` / ``summary.json``, print the table.

    Args:
        config: YAML config of a family.
        items: ``key=v1,v2`` swept keys and ``key=v`` fixed overrides.
        out_dir: sweep folder; point ``p`` writes ``out_dir/p.name/``.
        backend: ``local`` (in-process) or ``ray`` (one Ray task per point).
        quick: apply the config's ``experiment.quick_overrides`` first.
        address: Ray cluster address (default: a local Ray).
        workers: CPUs of the local Ray (default: all cores).
        progress: a progress bar over completed points.
        plots: each point draws its PNGs (``taskvar plot`` draws them later).
        overwrite: replace a sweep already in ``out_dir``.
        resume: keep the points already complete (:func:`completed_points`), run the others.
        batch_seeds: train points differing only in consecutive seeds as one run
            (:func:`seed_batches`).

    Returns the summary rows. Raises a one-line ``ValueError`` for an unknown backend or key, an
    empty value, a missing Ray, or a folder already holding a sweep (without ``overwrite`` or
    ``resume``).
    """
    _check_backend(backend, address, workers)
    if resume and overwrite:
        raise ValueError(
            "--resume keeps the completed points and --overwrite replaces them: give one of them"
        )
    points = expand_points(items)
    cfgs = load_point_configs(config, points, quick=quick)
    for c in cfgs:  # every point runs its family's figure experiment (Family.experiment)
        family(c).needs("experiment", "taskvar sweep")
    if backend == "ray":
        try:
            import ray  # noqa: F401  (fail before any work)
        except ImportError:
            raise ValueError(RAY_MISSING) from None
    out = check_out_path(out_dir).resolve()  # Ray workers need not share this working folder
    check_output_folder(out)  # a file, or under one, or read-only: one line before any run
    done = completed_points(out, points, cfgs) if resume else {}
    markers = (SUMMARY_JSON, SUMMARY_CSV, BATCHES, *(p.name for p in points))
    hint = "continue the sweep with --resume (complete points are kept), "
    folder = ResultsFolder(out, overwrite, "taskvar sweep", markers, hint=hint)
    if not resume:
        folder.check()  # a sweep already there, or a folder of other files (--out . in a project)
    if not (overwrite and any(os.path.lexists(out / m) for m in markers)):
        # a new sweep, or --resume: its points written in place, like train, so a killed sweep
        # resumes (else the old sweep is replaced whole: staged, swapped in at the end)
        folder = ResultsFolder(out, staged=False)
    with folder as dest:
        return _sweep(
            config, items, out, dest, points, cfgs, done, backend, quick, address, workers,
            progress, plots, overwrite, resume, batch_seeds,
        )  # fmt: skip


def _sweep(
    config: str | os.PathLike,
    items: Sequence[str],
    dest: Path,
    out: Path,
    points: Sequence[SweepPoint],
    cfgs: Sequence[Config],
    done: dict[int, dict[str, Any]],
    backend: str,
    quick: bool,
    address: str | None,
    workers: int | None,
    progress: bool,
    plots: bool,
    overwrite: bool,
    resume: bool,
    batch_seeds: bool,
) -> list[dict[str, Any]]:
    """:func:`sweep` once its inputs are checked, writing into ``out`` (``dest`` itself, or the
    staging folder of ``dest``); the summary names the points' folders in ``dest``."""
    todo = [i for i in range(len(points)) if i not in done]
    jobs, notes = plan_jobs(points, cfgs, todo, out, batch_seeds)
    if done:
        print(f"resuming {out}: {len(done)} of {len(points)} points complete, running {len(todo)}")
    for note in notes:
        print(note)
    batches = [j for j in jobs if j.batch is not None]
    if batches:
        print(
            f"seed batches: {len(batches)} training run(s) for {sum(len(j.points) for j in batches)}"
            f" points in {out / BATCHES} (--no-batch-seeds: one run per point)"
        )
    t0 = time.perf_counter()
    # a resumed point's partial folder (a killed run) is replaced: overwrite
    if backend == "local":
        ran = _run_local(jobs, quick, progress, plots, overwrite or resume)
    else:
        ran = _run_ray(jobs, quick, progress, address, workers, plots)
    wall = time.perf_counter() - t0
    results = [done[i] if i in done else None for i in range(len(points))]
    for i, r in zip([i for j in jobs for i in j.points], ran):
        results[i] = r
    rows = summary_rows(points, results)
    fields = list(dict.fromkeys(k for row in rows for k in row))
    write_csv(out / SUMMARY_CSV, rows, fields)
    summary = {
        "config": str(config),
        "experiment": sorted({family(c).experiment.name for c in cfgs}),
        "backend": backend,
        "quick": bool(quick),
        "plots": bool(plots),
        "batch_seeds": bool(batch_seeds),
        "items": list(items),
        "wall_seconds": wall,
        "points": [
            {
                "name": p.name,
                "folder": str(dest / p.name),
                "values": p.values,
                "overrides": list(p.overrides),
                "seconds": r["seconds"],
                "error": r.get("error"),
                "kept": i in done,  # complete before this run (resume)
                "batch": ((r.get("metrics") or {}).get("train_batch") or {}).get("folder"),
            }
            for i, (p, r) in enumerate(zip(points, results))
        ],
        "rows": rows,
    }
    write_json(out / SUMMARY_JSON, summary)
    print(format_summary(rows, fields))
    print(
        f"{len(rows)} points in {wall:.1f} s ({backend}); wrote {out / SUMMARY_CSV}, "
        f"{out / SUMMARY_JSON}"
    )
    return rows


def _check_backend(backend: str, address: str | None, workers: int | None) -> None:
    """One-line errors for a backend and its options that do not fit together."""
    if backend not in BACKENDS:
        raise ValueError(f"--backend must be one of {list(BACKENDS)}, got {backend!r}")
    if backend == "local" and (address is not None or workers is not None):
        raise ValueError(
            "--address and --workers are for --backend ray; local runs one point at a time"
        )
    if address is not None and workers is not None:
        raise ValueError(
            "--workers sets the CPUs of a local Ray; with --address the cluster's are used"
        )
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
