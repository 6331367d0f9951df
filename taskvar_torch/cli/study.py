"""``taskvar experiment``, ``sweep``, ``plot`` and ``report``: the paper's experiments, grids of
them, their figures and the claims page (thin wrappers over the experiment registry and the study
modules, each imported inside its command)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from typing import Any

from taskvar_torch.cli.arguments import (
    Command,
    overwrite_argument,
    set_threads,
    split_config_and_overrides,
)
from taskvar_torch.experiments.registry import EXPERIMENTS as _EXPERIMENTS
from taskvar_torch.experiments.registry import (
    experiment,
    experiment_of_folder,
    load_experiment_config,
)

EXPERIMENTS = tuple(_EXPERIMENTS)  # the experiment registry's names (experiments/registry.py)


def _experiment_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", choices=EXPERIMENTS, help="experiment")
    p.add_argument(
        "items",
        nargs="*",
        metavar="[CONFIG] [key.sub=value ...]",
        help="YAML config (default: the experiment's), then overrides",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="results folder (default: results/NAME, or results/NAME-quick with --quick)",
    )
    p.add_argument("--checkpoint", metavar="PATH", help="evaluate this bundle instead of training")
    overwrite_argument(p, "DIR (windy-fig2: DIR/train)")
    p.add_argument("--quick", action="store_true", help="apply experiment.quick_overrides")
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="N",
        help="wargus-fig4: split the repetitions into N batches, one process each (default 1: all in one batch)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="windy-fig2, scale: torch CPU threads (default 1, as the documented timings; the "
        "large grids' learner gains from 2 free cores, docs/scale.md); wargus-fig4 runs one "
        "thread per --workers process",
    )
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.add_argument(
        "--no-plots", action="store_true", help="write no PNGs (taskvar plot DIR draws them later)"
    )


def _experiment_run(args: argparse.Namespace) -> int:
    """``taskvar experiment NAME``: every experiment through its registry entry
    (experiments/registry.py); an option it does not take is a one-line error."""
    exp = experiment(args.name)
    options: dict[str, Any] = {
        "progress": not args.no_progress,
        "plots": not args.no_plots,
        "overwrite": args.overwrite,
    }
    if args.checkpoint is not None:
        exp.refuse("checkpoint", "--checkpoint")
        options["checkpoint"] = args.checkpoint
    if args.quick and exp.takes("quick"):  # --quick otherwise only picks the quick overrides
        options["quick"] = True
    if args.workers != 1:
        exp.refuse("workers", "--workers")
        cores = os.cpu_count() or 1
        if args.workers > cores:  # >= 1 is checked by the experiment
            raise ValueError(
                f"--workers must be in [1, {cores}] (this machine's cores), got {args.workers}"
            )
        options["workers"] = args.workers
    if args.threads != 1 and "threads" in dict(exp.refusals):  # e.g. one thread per worker
        raise ValueError(dict(exp.refusals)["threads"])
    set_threads(args)  # default 1: small MLPs, more threads only contend on a shared CPU
    config_path, overrides = split_config_and_overrides(args.items)
    if args.checkpoint is not None:
        overrides, controller = _check_checkpoint_overrides(overrides)
        if controller:  # played by the bundle's controllers (config/controller.py)
            exp.refuse("controller", "controller settings (train.KEY=VALUE)")
            options["controller"] = controller
        if config_path is not None:  # its env/heads/train keys would be ignored
            raise ValueError(
                f"config file {config_path!r} cannot apply with --checkpoint: the bundle's own "
                "config is used; pass experiment.*, eval.* or device overrides instead"
            )
    cfg = load_experiment_config(
        exp, config_path or exp.default_config_path(), overrides, quick=args.quick
    )
    out = args.out or f"results/{args.name}{'-quick' if args.quick else ''}"
    exp.call(cfg, out, **options)
    return 0


CHECKPOINT_OVERRIDABLE = ("experiment", "eval", "device")
"""Config sections an override may change when ``experiment --checkpoint`` evaluates a bundle
(the rest comes from the bundle's own config, but for the controller settings,
``config/controller.py``)."""


def _check_checkpoint_overrides(overrides: Sequence[str]) -> tuple[list[str], list[str]]:
    """The overrides of a ``--checkpoint`` run split into the config's (experiment.*, eval.*,
    device) and the controller settings applied to the bundle's config; any other (e.g.
    ``env.layout=...``, which the run would ignore) is a one-line error."""
    from taskvar_torch.config.controller import CONTROLLER_KEYS

    kept, controller = [], []
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if key in CONTROLLER_KEYS:
            controller.append(item)
        elif any(key == k or key.startswith(k + ".") for k in CHECKPOINT_OVERRIDABLE):
            kept.append(item)
        else:
            raise ValueError(
                f"override {item!r} cannot apply with --checkpoint: the bundle's own config is "
                f"used; only {', '.join(k + ('.*' if k != 'device' else '') for k in CHECKPOINT_OVERRIDABLE)} "
                f"and the controller settings {', '.join(CONTROLLER_KEYS)} may be overridden "
                "(train a new bundle to change it)"
            )
    return kept, controller


def _sweep_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "config",
        metavar="CONFIG",
        help="YAML config of a family: windy runs windy-fig2, wargus runs wargus-fig4",
    )
    p.add_argument(
        "items",
        nargs="*",
        metavar="key.sub=v1,v2,...",
        help="swept keys (comma-separated values; the points are their Cartesian product) and "
        "fixed overrides (key.sub=value)",
    )
    p.add_argument(
        "--backend",
        required=True,
        choices=("local", "ray"),
        help="local: the points one after the other in this process; ray: one Ray task "
        "(1 CPU) per point",
    )
    p.add_argument("--address", metavar="ADDR", help="ray: a Ray cluster (default: a local Ray)")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="ray: CPUs of the local Ray, i.e. points at once (default: all cores)",
    )
    p.add_argument("--quick", action="store_true", help="apply experiment.quick_overrides")
    p.add_argument(
        "--out",
        default="results/sweep",
        metavar="DIR",
        help="sweep folder: DIR/<point>/ per point, DIR/summary.csv, DIR/summary.json "
        "(default: results/sweep)",
    )
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument(
        "--no-plots",
        action="store_true",
        help="points write no PNGs (faster; taskvar plot DIR/<point> draws them later)",
    )
    overwrite_argument(p, "DIR (the sweep and its points)")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue a sweep already in DIR (e.g. killed part-way): points whose folder holds "
        "metrics.json and the same config.yaml are kept, the others run (docs/sweeps.md)",
    )
    p.add_argument(
        "--no-batch-seeds",
        action="store_true",
        help="train every point alone (default: points differing only in consecutive seeds "
        "train as one train.seeds=k run in DIR/batches/, docs/sweeps.md)",
    )


def _sweep_run(args: argparse.Namespace) -> int:
    from taskvar_torch.study.sweep import sweep

    sweep(
        args.config,
        args.items,
        args.out,
        backend=args.backend,
        quick=args.quick,
        address=args.address,
        workers=args.workers,
        progress=not args.no_progress,
        plots=not args.no_plots,
        overwrite=args.overwrite,
        resume=args.resume,
        batch_seeds=not args.no_batch_seeds,
    )
    return 0


def _plot_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("results", metavar="DIR", help="a results folder of taskvar experiment")


def _plot_run(args: argparse.Namespace) -> int:
    from taskvar_torch.run_folder import ResultsFolder

    exp = experiment_of_folder(args.results)
    with ResultsFolder(args.results, staged=False, flag="DIR"):  # not while a command writes it
        paths = exp.plot_results(args.results)
    for path in paths:
        print(path)
    return 0


def _report_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "dirs",
        nargs="+",
        metavar="DIR",
        help="results folders of taskvar experiment (windy-fig2, wargus-fig4, scale) or taskvar "
        "eval --out, or folders of seed<k>/ results folders (one training seed each)",
    )
    p.add_argument(
        "--out",
        metavar="FILE",
        help="the claims page (docs/claims.md); beside it img/<FILE stem>-profile.png "
        "(performance profiles), img/<FILE stem>-results.png (regret per method and family) and "
        "<FILE stem>-results.json (the data of the Results page's compact tables) (required "
        "unless --add)",
    )
    p.add_argument(
        "--page",
        "--readme",
        dest="page",
        metavar="FILE",
        help="also replace the Results block between <!-- report:results:start --> and "
        "<!-- report:results:end --> in FILE (docs/results.md; --readme: its older name): the "
        "regret figure, per family a compact table (methods as columns, the best mean bold, ≈ "
        "not separated from it) and the table of every result, folded. A FILE that does not "
        "exist is written as a page of its own; one without the markers is left alone and the "
        "Results go to results.md beside the claims page instead (said on stdout)",
    )
    p.add_argument(
        "--reps", type=int, default=2000, help="bootstrap resamples per CI (default 2000)"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an --out page or profile PNG that taskvar report did not write",
    )
    p.add_argument(
        "--add",
        action="store_true",
        help="only add these folders' rows to the --page Results table (a row of the same "
        "experiment and config is replaced, the others kept) and write no claims page; for "
        "results that score none of the paper's claims (--out: the claims page whose "
        "<stem>-results.json keeps the rows' data, default claims.md beside the page where it "
        "is there or the page is in docs/, else docs/claims.md under its folder)",
    )
    p.add_argument(
        "--mixed-commits",
        action="store_true",
        help="report results computed at different commits together (metrics.json's "
        "code.commit; by default they are refused, naming both)",
    )
    p.add_argument(
        "--drop",
        metavar="DIGEST",
        action="append",
        default=[],
        help="with --add: remove the rows of this config digest (the table's config column), "
        "results a rerun supersedes; repeatable",
    )


def _report_run(args: argparse.Namespace) -> int:
    from taskvar_torch.study.report import CLAIMS, ReportError, add_rows, write_report

    if args.add:
        if args.page is None:
            raise ReportError(
                "--add needs --readme/--page FILE: the page whose Results table grows "
                "(docs/results.md)"
            )
        written, report = add_rows(
            args.dirs, args.page, args.out, args.reps, args.drop, args.mixed_commits
        )
        for note in report.notes:
            print(note)
        print("wrote " + ", ".join(str(p) for p in written))
        return 0
    if args.drop:
        raise ReportError("--drop goes with --add (a claims page is rewritten from every folder)")
    if args.out is None:
        raise ReportError("--out FILE is required (the claims page, docs/claims.md) unless --add")
    written, report = write_report(
        args.dirs, args.out, args.page, args.reps, args.overwrite, args.mixed_commits
    )
    for c in report.claims:
        print(f"{CLAIMS[c.key][0]} [{c.group}]: {c.verdict} ({c.reason})")
    for note in report.notes:
        print(note)
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


EXPERIMENT = Command(
    help="run one of the paper's experiments (windy-fig2, wargus-fig4, scale)",
    description="Train (or load --checkpoint), evaluate, write a results folder and print a table.",
    add_arguments=_experiment_arguments,
    run=_experiment_run,
)


SWEEP = Command(
    help="run an experiment over a grid of config overrides (local or Ray)",
    description="Run the config family's experiment (windy-fig2 or wargus-fig4) once per "
    "point of the Cartesian product of key=v1,v2 values, locally or as Ray tasks; print and "
    "write a summary table (DIR/summary.csv, DIR/summary.json).\n\n"
    "  taskvar sweep configs/windy.yaml --backend ray --quick --out results/sweep seed=0,1",
    add_arguments=_sweep_arguments,
    run=_sweep_run,
)


PLOT = Command(
    help="redraw the figures of an experiment's results folder",
    description="(Re)draw the PNG figures of a results folder.",
    add_arguments=_plot_arguments,
    run=_plot_run,
)


REPORT = Command(
    help="regenerate the paper's claims page and the Results page's tables from results",
    description="Read results folders (training seeds; fewer than 5: an exploratory table, no "
    "claims), aggregate them with rliable on each result's own test distribution (the claims on "
    "the sealed held-out instances only) and write the claims page (the paper's figure, ours "
    "with its 95% CI, a verdict), its performance profiles and, with --page, the Results "
    "tables (docs/report.md).\n\n"
    "  taskvar report results/fig2-seeds results/fig4 --out docs/claims.md --page docs/results.md",
    add_arguments=_report_arguments,
    run=_report_run,
)
