"""Sweeps: one experiment per point of a grid of config overrides, run locally or on Ray.

``taskvar sweep CONFIG --backend local|ray [--quick] [--out DIR] key=v1,v2 ...``: the config names
a family (``windy`` runs the windy Figure 2 experiment, ``wargus`` the Wargus Figure 4 one, paper
§3.3.1 and §3.5); every ``key=v1,v2,...`` with a comma is a swept key, the points are the Cartesian
product of their values (``seed=0,1`` gives two repetitions), and a plain ``key=value`` is a fixed
override of every point. Each point runs the same function as ``taskvar experiment`` into its own
folder ``OUT/<point name>/``; at the end a summary table (swept values and headline metrics) is
printed and written to ``OUT/summary.csv`` and ``OUT/summary.json``.

Backends (:data:`BACKENDS`):

- ``local``: the points one after the other in this process;
- ``ray``: each point is a Ray task with ``num_cpus=1`` (one torch thread), on a local Ray started
  with ``workers`` CPUs (default: all cores) or on the cluster at ``address``.

A point's numbers depend only on its config (every random stream is seeded from ``cfg.seed``), so
both backends give the same metrics.

Seed batches (``batch_seeds=True``, the default; ``--no-batch-seeds`` turns it off): points whose
configs differ only in ``seed``, with consecutive seeds, are trained as *one* run with
``train.seeds = k`` (the batched trainer, docs/seeds.md) in ``OUT/batches/<name>/``; each point
then evaluates its seed's bundle: ``OUT/<point>/train`` is a relative symlink to the batch's
``seed<i>/`` folder, so the point holds the same files and keys as an unbatched one
(:func:`seed_batches`). This needs an experiment that evaluates a given bundle (windy-fig2's
``checkpoint``; wargus-fig4 trains in its own loop) and a config the batched trainer takes; other
points, and seeds that are not consecutive, run one by one (a printed note says why).

Resuming (``resume=True``, ``taskvar sweep ... --resume``): a sweep killed part-way is rerun with
the same ``--out``; a point is complete when its folder holds ``metrics.json`` and its
``config.yaml`` equals the config the sweep would run (:func:`completed_points`). Complete points
are kept (their metrics read back for the summary), the others run again from scratch (a killed
point's partial folder is replaced). A point folder holding results of another config is refused.
Without ``resume`` or ``overwrite`` a folder already holding a sweep is refused.

Examples:
    >>> points = expand_points(["seed=0,1", "train.lr=0.002"])
    >>> [p.name for p in points]
    ['seed=0', 'seed=1']
    >>> points[1].overrides
    ('train.lr=0.002', 'seed=1')
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import itertools
import json
import os
import re
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from taskvar_torch.config import Config, apply_overrides, config_to_dict, load_config
from taskvar_torch.experiments.registry import experiment
from taskvar_torch.experiments.results import refuse_existing_results, write_csv, write_json
from taskvar_torch.families import family
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import ResultsFolder, check_out_path, check_output_folder, folder_lock
from taskvar_torch.training import TrainingDiverged, train

BACKENDS = ("local", "ray")
"""Config family -> the experiment each sweep point runs (as ``taskvar experiment NAME``)."""
RAY_MISSING = 'taskvar sweep --backend ray needs Ray: pip install "taskvar-torch[distributed]"'
SUMMARY_CSV, SUMMARY_JSON, POINT_LOG = "summary.csv", "summary.json", "output.txt"
BATCHES = "batches"
"""``OUT/batches/<name>/``: the training run of a seed batch (``train.seeds = k``)."""
RAY_RETRIES = 1
"""Ray backend: a point whose worker process dies is run again this many times, then recorded as
failed (its summary row's ``error``; the sweep goes on)."""


@dataclass(frozen=True)
class SweepPoint:
    """One point: its folder name, its swept values and every override it applies (in order)."""

    name: str
    values: dict[str, str]
    overrides: tuple[str, ...]


# --------------------------------------------------------------------------------------------
# points


def split_values(text: str) -> list[str]:
    """``'0,1'`` -> ``['0', '1']``; commas inside ``[...]``, ``{...}`` or quotes do not split."""
    parts, depth, quote, start = [], 0, "", 0
    for i, c in enumerate(text):
        if quote:
            quote = "" if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c in "[{":
            depth += 1
        elif c in "]}":
            depth -= 1
        elif c == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return [p.strip() for p in parts]


def point_name(values: dict[str, str]) -> str:
    """Folder name of a point: ``key=value`` pairs joined by ``,``, other characters as ``_``."""
    if not values:
        return "run"
    text = ",".join(f"{k}={v}" for k, v in values.items())
    return re.sub(r"[^A-Za-z0-9._=,+-]", "_", text)


def expand_points(items: Sequence[str]) -> list[SweepPoint]:
    """The Cartesian product of the swept keys (``key=v1,v2``), fixed overrides (``key=v``) first.

    Raises:
        ValueError: an item without ``=``, an empty value, or a key given twice.
    """
    fixed: list[str] = []
    swept: dict[str, list[str]] = {}
    seen: set[str] = set()
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"sweep override {item!r} must look like key.sub=v1,v2,... ")
        if key in seen:
            raise ValueError(f"sweep key {key!r} is given twice; give its values once: {key}=v1,v2")
        seen.add(key)
        values = split_values(text)
        if any(v == "" for v in values):
            raise ValueError(
                f"sweep key {key!r} has an empty value in {text!r}; give {key}=v1,v2,... "
                "with non-empty values"
            )
        if len(values) == 1:
            fixed.append(f"{key}={values[0]}")
        else:
            swept[key] = values
    points, names = [], set()
    for combo in itertools.product(*swept.values()):
        values = dict(zip(swept, combo))
        name = point_name(values)
        if name in names:  # two values that differ only in unsafe characters
            name = f"{name},{len(points)}"
        names.add(name)
        points.append(SweepPoint(name, values, (*fixed, *(f"{k}={v}" for k, v in values.items()))))
    return points


def load_point_configs(
    config: str | os.PathLike, points: Sequence[SweepPoint], quick: bool = False
) -> list[Config]:
    """Every point's config, strictly loaded (the config loader's one-line errors, before any run)."""
    cfgs = []
    for p in points:
        try:
            cfgs.append(load_config(config, p.overrides, quick=quick))
        except ValueError as e:
            raise ValueError(f"{e} [sweep point {p.name}]" if p.values else str(e)) from None
    return cfgs


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
    """Run ``cfg``'s family experiment into ``out_dir``; its printed table goes to ``output.txt``.

    ``plots=False`` skips the experiment's PNGs (``taskvar plot out_dir`` draws them later);
    ``checkpoint``: evaluate this bundle instead of training (a seed batch's, :func:`run_batch`).

    Returns:
        ``{"metrics": metrics.json's dict, "seconds": wall time}``; a diverged run returns
        ``{"error": message, "seconds": ...}`` instead (the sweep goes on).
    """

    torch.set_num_threads(1)  # one core per point (the heads are small MLPs)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if checkpoint is None and (out / "train").is_symlink():
        (out / "train").unlink()  # a killed batched attempt's link: this point now trains alone
    t0 = time.perf_counter()
    exp = experiment(family(cfg).experiment)
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
    exp = experiment(family(cfg).experiment)
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
    """The seed batches among the points ``todo``: lists of >= 2 point indices whose configs are
    equal but for ``seed`` and whose seeds are consecutive (sorted: ``seed, seed + 1, ...``, the
    batched trainer's rule), and one note for each group of such points that is not (or not
    wholly) batched, saying why."""
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
    """Train the points ``cfgs`` (consecutive seeds of one config) as one ``train.seeds = k`` run
    in ``batch_dir`` (its printed lines in ``output.txt`` there), then run each point's
    experiment on its seed's bundle: ``outs[i]/train`` becomes a relative symlink to
    ``batch_dir/seed<i>``, so the point folder reads as an unbatched one.

    Each point's ``metrics.json`` gains ``train_batch`` (the batch folder relative to the point,
    its seeds and the point's index); its ``train_seconds`` is its share of the batch's training
    time (the batch's / k) and ``wall_seconds`` (and the summary's seconds) add that share.
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


def headline(metrics: dict[str, Any]) -> dict[str, Any]:
    """The summary-table numbers of one point's ``metrics.json``.

    Windy Figure 2: fraction no worse and mean difference (interruption - averaging), the null's
    and the exact (oracle) fraction no worse, for the training distribution and south-only winds. Wargus Figure 4: each method's final score and trials to 90%.
    """
    if metrics.get("experiment") == "windy-fig2":
        keys = (
            "fraction_no_worse",
            "mean_difference",
            "fraction_no_worse_null",
            "fraction_no_worse_exact",
        )
        row = {k: metrics.get(k) for k in keys}
        south = metrics.get("south_only") or {}
        row.update({f"south_only.{k}": south.get(k) for k in keys})
        return row
    row = {f"final_score.{n}": m["final_score"] for n, m in metrics["methods"].items()}
    row.update(
        {f"trials_to_90pct.{n}": m["trials_to_90pct"] for n, m in metrics["methods"].items()}
    )
    return row


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
        config: YAML config of a family (windy or wargus).
        items: ``key=v1,v2`` swept keys and ``key=v`` fixed overrides.
        out_dir: sweep folder; point ``p`` writes ``out_dir/p.name/``.
        backend: ``local`` (in-process, sequential) or ``ray`` (one Ray task per point).
        quick: apply the config's ``experiment.quick_overrides`` (before the sweep's).
        address: Ray cluster address (``ray`` only; default: start a local Ray).
        workers: CPUs of the local Ray (``ray`` only; default: all cores).
        progress: a progress bar over completed points.
        plots: each point draws its PNGs (``False``: skipped, about half of a small windy point's
            time; ``taskvar plot out_dir/<point>`` draws them later).
        overwrite: replace a sweep (and its points) already in ``out_dir``; without it (or
            ``resume``) such a folder is refused.
        resume: keep the points already complete in ``out_dir`` (:func:`completed_points`), run
            the others (a partial point folder is replaced).
        batch_seeds: train the points that differ only in (consecutive) seeds as one batched run
            (:func:`seed_batches`, ``OUT/batches/``); ``False``: every point trains alone.

    Returns:
        The summary rows (one per point).

    Raises:
        ValueError: one line, for an unknown backend or key, an empty value, a missing Ray, a
            folder already holding a sweep (without ``overwrite`` or ``resume``).
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
    folder = ResultsFolder(out, overwrite, "taskvar sweep", markers)
    if not resume:
        _refuse_existing_sweep(out, points, overwrite)
        folder.check()  # and a folder of other files (--out . in a project)
    if overwrite and any(os.path.lexists(out / m) for m in markers):
        # replaced whole: written in a staging folder, swapped in at the end (ResultsFolder)
        with folder as staging:
            return _sweep(
                config, items, out, staging, points, cfgs, done, backend, quick, address,
                workers, progress, plots, overwrite, resume, batch_seeds,
            )  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)  # a new sweep, or --resume: in place, like train
    with folder_lock(out):
        return _sweep(
            config, items, out, out, points, cfgs, done, backend, quick, address, workers,
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
    rows = _summary_rows(points, results)
    fields = list(dict.fromkeys(k for row in rows for k in row))
    write_csv(out / SUMMARY_CSV, rows, fields)
    summary = {
        "config": str(config),
        "experiment": sorted({family(c).experiment for c in cfgs}),
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


def completed_points(
    out: Path, points: Sequence[SweepPoint], cfgs: Sequence[Config]
) -> dict[int, dict[str, Any]]:
    """The points already complete in ``out``: ``{index: {"metrics": ..., "seconds": ...}}``.

    A point is complete when ``out/<point>/metrics.json`` exists and ``out/<point>/config.yaml``
    equals the point's config. A point folder without ``metrics.json`` (a killed run) is not
    complete.

    Raises:
        ValueError: a point folder holds results (``metrics.json``) of another config, or an
            unreadable ``metrics.json`` / ``config.yaml``.
    """
    done: dict[int, dict[str, Any]] = {}
    for i, (p, cfg) in enumerate(zip(points, cfgs)):
        folder = out / p.name
        if not (folder / "metrics.json").is_file():
            continue
        try:
            saved = OmegaConf.to_container(OmegaConf.load(folder / "config.yaml"))
            metrics = json.loads((folder / "metrics.json").read_text())
        except Exception as e:  # a missing or damaged file: not this sweep's complete point
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ValueError(
                f"--resume: point folder {str(folder)!r} holds metrics.json but its config.yaml "
                f"or metrics.json cannot be read ({first}); remove the folder or use --overwrite"
            ) from None
        wanted = config_to_dict(cfg)
        if saved != wanted:
            key = _first_difference(saved, wanted)
            raise ValueError(
                f"--resume: point folder {str(folder)!r} holds results of another config "
                f"({key} differs); this is not the same sweep: use --overwrite or another --out"
            )
        seconds = metrics.get("wall_seconds", (metrics.get("timing") or {}).get("wall_seconds"))
        done[i] = {"metrics": metrics, "seconds": seconds}
    return done


def _first_difference(a: Any, b: Any, prefix: str = "") -> str:
    """The first dotted key whose value differs between two nested dicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in list(a) + [k for k in b if k not in a]:
            if a.get(k, "<absent>") != b.get(k, "<absent>"):
                return _first_difference(a.get(k), b.get(k), f"{prefix}{k}.")
    return prefix.rstrip(".") or "config"


def _refuse_existing_sweep(out: Path, points: Sequence[SweepPoint], overwrite: bool) -> None:
    """One line when ``out`` already holds a sweep (its summary, or a point folder with files) or
    an experiment's results."""
    if overwrite or not out.is_dir():
        return
    found = [n for n in (SUMMARY_JSON, SUMMARY_CSV) if (out / n).exists()]
    found += [p.name for p in points if (out / p.name).is_dir() and any((out / p.name).iterdir())]
    if (out / BATCHES).is_dir() and any((out / BATCHES).iterdir()):
        found.append(BATCHES)
    if found:
        raise ValueError(
            f"--out {str(out)!r} already holds results ({', '.join(found[:4])}"
            f"{', ...' if len(found) > 4 else ''}); continue the sweep with --resume (complete "
            "points are kept), replace it with --overwrite, or choose another --out"
        )
    refuse_existing_results(out, overwrite, "taskvar sweep")


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


def _summary_rows(points: Sequence[Any], results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One summary row per point: its swept values, headline numbers, seconds (and error)."""
    rows = []
    for p, r in zip(points, results):
        row: dict[str, Any] = {"point": p.name, **p.values}
        row.update(headline(r["metrics"]) if "metrics" in r else {})
        row["seconds"] = r["seconds"]
        if any("error" in x for x in results):
            row["error"] = r.get("error", "")
        rows.append(row)
    return rows


def format_summary(rows: Sequence[dict[str, Any]], fields: Sequence[str]) -> str:
    """Aligned text table of the summary rows (floats to 3 decimals)."""

    def cell(v: Any) -> str:
        return f"{v:.3f}" if isinstance(v, float) else ("" if v is None else str(v))

    table = [list(fields)] + [[cell(r.get(f)) for f in fields] for r in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(fields))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(line, widths)).rstrip() for line in table)
