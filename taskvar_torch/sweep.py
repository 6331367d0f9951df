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
import itertools
import json
import os
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from taskvar_torch.config import Config, config_to_dict, load_config
from taskvar_torch.experiments.registry import experiment
from taskvar_torch.experiments.results import refuse_existing_results, write_csv, write_json
from taskvar_torch.families import family
from taskvar_torch.progress import progress_bar
from taskvar_torch.train import TrainingDiverged, check_output_folder

BACKENDS = ("local", "ray")
"""Config family -> the experiment each sweep point runs (as ``taskvar experiment NAME``)."""
RAY_MISSING = 'taskvar sweep --backend ray needs Ray: pip install "taskvar-torch[distributed]"'
SUMMARY_CSV, SUMMARY_JSON, POINT_LOG = "summary.csv", "summary.json", "output.txt"
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
    cfg: Config, out_dir: str, quick: bool = False, plots: bool = True, overwrite: bool = False
) -> dict[str, Any]:
    """Run ``cfg``'s family experiment into ``out_dir``; its printed table goes to ``output.txt``.

    ``plots=False`` skips the experiment's PNGs (``taskvar plot out_dir`` draws them later).

    Returns:
        ``{"metrics": metrics.json's dict, "seconds": wall time}``; a diverged run returns
        ``{"error": message, "seconds": ...}`` instead (the sweep goes on).
    """

    torch.set_num_threads(1)  # one core per point (the heads are small MLPs)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(out / POINT_LOG, "w") as log, contextlib.redirect_stdout(log):
        try:
            metrics = experiment(family(cfg).experiment).call(
                cfg, out, workers=1, progress=False, quick=quick, plots=plots, overwrite=overwrite
            )
        except TrainingDiverged as e:
            print(f"error: {e}")
            return {"error": f"TrainingDiverged: {e}", "seconds": time.perf_counter() - t0}
    return {"metrics": metrics, "seconds": time.perf_counter() - t0}


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
    jobs: list[tuple[Config, str]], quick: bool, progress: bool, plots: bool, overwrite: bool
) -> list[dict[str, Any]]:
    return [
        run_point(cfg, out, quick, plots, overwrite)
        for cfg, out in progress_bar(jobs, disable=not progress, desc="sweep", unit="point")
    ]


def _run_ray(
    jobs: list[tuple[Config, str]],
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
        task = ray.remote(num_cpus=1, max_retries=RAY_RETRIES)(run_point)
        refs = [task.remote(cfg, out, quick, plots, True) for cfg, out in jobs]
        pending = list(refs)
        with progress_bar(total=len(refs), disable=not progress, desc="sweep", unit="point") as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                bar.update(len(done))
        return [_ray_result(ray, ref) for ref in refs]
    finally:
        if started:
            ray.shutdown()


def _ray_result(ray: Any, ref: Any) -> dict[str, Any]:
    """A task's result; a task whose worker died on every try is a failed point (its error)."""
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
    out = Path(out_dir).resolve()  # Ray workers need not share this process's working folder
    check_output_folder(out)  # a file, or under one, or read-only: one line before any run
    done = completed_points(out, points, cfgs) if resume else {}
    if not resume:
        _refuse_existing_sweep(out, points, overwrite)
    out.mkdir(parents=True, exist_ok=True)
    todo = [i for i in range(len(points)) if i not in done]
    jobs = [(cfgs[i], str(out / points[i].name)) for i in todo]
    if done:
        print(f"resuming {out}: {len(done)} of {len(points)} points complete, running {len(todo)}")
    t0 = time.perf_counter()
    # a resumed point's partial folder (a killed run) is replaced: overwrite
    if backend == "local":
        ran = _run_local(jobs, quick, progress, plots, overwrite or resume)
    else:
        ran = _run_ray(jobs, quick, progress, address, workers, plots)
    wall = time.perf_counter() - t0
    results = [done[i] if i in done else None for i in range(len(points))]
    for i, r in zip(todo, ran):
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
        "items": list(items),
        "wall_seconds": wall,
        "points": [
            {
                "name": p.name,
                "folder": str(out / p.name),
                "values": p.values,
                "overrides": list(p.overrides),
                "seconds": r["seconds"],
                "error": r.get("error"),
                "kept": i in done,  # complete before this run (resume)
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
