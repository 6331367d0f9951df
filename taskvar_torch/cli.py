"""Command line: ``taskvar COMMAND ...`` (train | eval | experiment | plot | sweep).

Each command is one entry of :data:`COMMANDS`: a help line, a function adding its arguments to an
``argparse`` parser, and a function running it. Commands parse *intermixed* arguments, so
Hydra-style ``key.sub=value`` overrides may come before or after the options::

    taskvar train configs/windy.yaml --out runs/windy train.total_frames=100000
    taskvar train --resume runs/windy/checkpoint_000050176.pt --out runs/windy
    taskvar train --help

Errors in the inputs (a misspelt config key, a foreign or tampered checkpoint, a diverged run, an
``--out`` that cannot be used, more memory than the machine has) print one line ``taskvar COMMAND:
error: ...`` and exit with status 2. Ctrl-C (SIGINT) or SIGTERM during ``taskvar train`` stops
after the current batch, writes a checkpoint and prints one line with the ``--resume`` command
(status 130, or 143 for SIGTERM); a second Ctrl-C aborts at once; elsewhere either signal prints
one line ``taskvar COMMAND: interrupted ...`` (128 + N). Any other exception is a bug in the
package: its traceback, then one line saying so (status 1). docs/reliability.md has them all.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from taskvar_torch.checkpoint import CheckpointError
from taskvar_torch.experiments.registry import EXPERIMENTS as _EXPERIMENTS
from taskvar_torch.experiments.registry import experiment, experiment_of_folder
from taskvar_torch.run_folder import check_out_path

# Each subcommand imports the machinery it runs inside its own function: the experiment modules
# share function names (default_config_path, plot_results, scale), and `taskvar --help` or a
# one-line error does not load every experiment.


@dataclass(frozen=True)
class Command:
    """A subcommand: ``help`` line, ``add_arguments(parser)``, ``run(args) -> exit status``."""

    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    epilog: Callable[[], str] | None = None


def _split_config_and_overrides(items: Sequence[str]) -> tuple[str | None, list[str]]:
    """``CONFIG`` is the first item without ``=``; the rest are ``key.sub=value`` overrides."""
    config, overrides = None, []
    for item in items:
        if "=" not in item and config is None:
            config = item
        elif "=" not in item:
            raise ValueError(f"expected key.sub=value overrides after the config, got {item!r}")
        else:
            overrides.append(item)
    return config, overrides


# --------------------------------------------------------------------------------------------
# taskvar train


def _train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--help-all",
        action=_HelpAll,
        help="list every config key, grouped by section, with each family's own, and exit",
    )
    p.add_argument(
        "items",
        nargs="*",
        metavar="CONFIG [key.sub=value ...]",
        help="YAML config (e.g. configs/windy.yaml; optional with --resume), then overrides",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="results folder (logs, checkpoints)")
    p.add_argument(
        "--resume",
        metavar="PATH",
        help="continue exactly from a checkpoint of a previous run (its config is used; only "
        "runtime keys such as train.total_frames may be overridden)",
    )
    p.add_argument(
        "--seeds",
        type=_seed_count,
        metavar="N",
        help="N independent training runs (seeds seed .. seed + N - 1) in one batched learner, "
        "written as DIR/seed<k>/ bundles (the config key train.seeds)",
    )
    _overwrite_argument(p, "DIR")
    _threads_argument(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _seed_count(text: str) -> int:
    """``--seeds``: a positive integer, else argparse's one-line error."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return n


def _train_epilog() -> str:
    from taskvar_torch.config.help import config_help, count_keys, user_help

    return (
        "the config keys a user sets (override any key with key.sub=value):\n"
        + user_help()
        + f"\n\ntaskvar train --help-all lists every key ({count_keys(config_help())}), "
        "grouped by section, with each family's own"
    )


class _HelpAll(argparse.Action):
    """``--help-all``: every config key, grouped by section, with each family's own; exits."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *args: Any, **kwargs: Any) -> None:
        from taskvar_torch.config import config_help

        print("every config key (override any with key.sub=value):\n" + config_help())
        parser.exit()


def _train_run(args: argparse.Namespace) -> int:
    from taskvar_torch.config import load_config
    from taskvar_torch.training import train

    _set_threads(args)
    config_path, overrides = _split_config_and_overrides(args.items)
    if config_path is None and args.resume is None:
        raise ValueError("give a CONFIG file (e.g. configs/windy.yaml) or --resume PATH")
    if getattr(args, "seeds", None) is not None:
        if args.resume is not None:
            raise ValueError("--seeds starts a new batch; --resume continues the checkpoint's own")
        overrides = [*overrides, f"train.seeds={args.seeds}"]
    cfg = load_config(config_path, overrides) if config_path is not None else None
    result = train(
        cfg,
        args.out,
        resume=args.resume,
        overrides=overrides if cfg is None else (),
        progress=not args.no_progress,
        overwrite=args.overwrite,
    )
    if "seeds" in result:  # train.seeds > 1: one bundle per seed
        print(
            f"trained {len(result['seeds'])} seeds, {result['updates']} updates on "
            f"{result['frames']} frames each, in {result['seconds']:.1f} s; bundles: "
            + ", ".join(str(p) for p in result["seeds"])
        )
        for path in result["seeds"]:
            _print_oracle_summary(path)
        return 0
    print(
        f"trained {result['updates']} updates on {result['frames']} frames in "
        f"{result['seconds']:.1f} s; final bundle: {result['final']}"
    )
    _print_oracle_summary(result["final"])
    return 0


def _print_oracle_summary(path: str | os.PathLike) -> None:
    """Where the family brings an exact oracle that covers the bundle's env, print the learnt
    heads beside it (``Family.oracle_summary``; windy: docs/oracle.md)."""
    from taskvar_torch.factory import load_heads
    from taskvar_torch.families import family

    heads, cfg = load_heads(path)
    summary = family(cfg).oracle_summary
    for line in summary(heads, cfg) if summary is not None else []:
        print(line)


# --------------------------------------------------------------------------------------------
# taskvar eval | experiment | plot (thin wrappers over taskvar_torch.experiments)


def _overwrite_argument(p: argparse.ArgumentParser, where: str) -> None:
    p.add_argument(
        "--overwrite",
        action="store_true",
        help=f"replace the run already in {where} (its config, checkpoints and logs are removed "
        "first); without it a folder holding a run is refused",
    )


def _threads_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="torch CPU threads (default 1: the heads are small MLPs, and more threads only "
        "contend on a shared CPU; raise it for large networks)",
    )


def _set_threads(args: argparse.Namespace) -> None:
    import torch

    cores = os.cpu_count() or 1
    if not 1 <= args.threads <= cores:
        raise ValueError(
            f"--threads must be in [1, {cores}] (this machine's cores), got {args.threads}"
        )
    torch.set_num_threads(args.threads)


def _eval_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--checkpoint",
        required=True,
        metavar="PATH",
        help="bundle of either family: taskvar train's final.pt, an experiment repetition's, or an "
        "exported heads.pt",
    )
    p.add_argument(
        "--method",
        default=None,
        help="all, or one or a comma list of averaging, options, interruption, hierarchy, "
        "recurrent, informed (the last two where DIR/recurrent.pt, DIR/informed.pt exist: "
        "taskvar train-baselines); every method plays the same paired episodes (default: "
        "interruption; all with --by-frames)",
    )
    p.add_argument("--episodes", type=int, default=1000, help="test episodes (default 1000)")
    p.add_argument(
        "--test",
        default=None,
        help="named test distribution of the bundle's family (docs/evaluation.md; windy: train, "
        "south, north, calm, stormy, ...; Wargus: nominal, train, fast_patrol, more_patrols, ...; "
        "heldout: the sealed held-out episodes); "
        "default: the family's first (windy train, Wargus nominal)",
    )
    p.add_argument(
        "--shift",
        action="append",
        default=[],
        metavar="KEY=V[,V2,...]",
        help="change an env key (env.wargus.patrol_speed=1.0) or an instance field "
        "(env.instances.p=0.5); several values sweep it and draw the shift curve; repeatable",
    )
    p.add_argument("--seed", type=int, help="test seed (default: the experiment's run 0)")
    p.add_argument(
        "--batch-size", type=int, metavar="N", help="episodes per batch (eval.batch_size)"
    )
    p.add_argument(
        "--exact",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="exact per-episode returns and regret where the family has an exact oracle; default: "
        "where they are cheap (Taxi: few distinct rain values); --exact always, --no-exact never",
    )
    p.add_argument(
        "--by-frames",
        action="store_true",
        help="also each memoryless method's exact regret against the per-instance optimum on every "
        "heads snapshot of the run (train.heads_every=N) and the final heads, on the same paired "
        "episodes: metrics.json regret_by_frames, DIR/regret_by_frames.csv and .png (windy, Taxi; "
        "docs/memory.md)",
    )
    p.add_argument("--out", metavar="DIR", help="write DIR/metrics.json, episodes.csv, eval.png")
    p.add_argument(
        "--explain",
        action="store_true",
        help="after the table, say in words what each column is and what the numbers show (which "
        "methods acted alike or tie within their 95%% CIs, memory against the memoryless methods, "
        "the ceiling), and where to read further (make demo uses it)",
    )
    _overwrite_argument(p, "DIR")
    _threads_argument(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _eval_run(args: argparse.Namespace) -> int:
    from taskvar_torch.experiments.bundle_eval import eval_bundle, explain_table, format_table
    from taskvar_torch.experiments.regret_frames import format_by_frames
    from taskvar_torch.experiments.shift import parse_shift

    _set_threads(args)
    test = None if args.test is None else _test_name(args.test)
    shifts = [parse_shift(s) for s in args.shift]  # one-line errors before any loading
    if args.batch_size is not None and args.batch_size < 1:  # 0 would fall back to the config's
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.out is not None:
        from taskvar_torch.run_folder import check_output_folder

        check_output_folder(args.out)
    method = args.method or ("all" if args.by_frames else "interruption")
    metrics = eval_bundle(
        args.checkpoint,
        method,
        test,
        shifts,
        episodes=args.episodes,
        seed=args.seed,
        batch_size=args.batch_size,
        exact=args.exact,
        out_dir=args.out,
        progress=not args.no_progress,
        overwrite=args.overwrite,
        by_frames=args.by_frames,
    )
    print(format_table(metrics))
    if args.by_frames:
        print(format_by_frames(metrics["regret_by_frames"]))
    if args.out is not None:
        print(
            f"wrote {args.out}/metrics.json, episodes.csv"
            + (", eval.png" if metrics.get("figures") else "")
            + "".join(f", {f}" for f in metrics.get("regret_by_frames", {}).get("files", []))
        )
    if args.explain:
        print(explain_table(metrics))
    return 0


def _test_name(name: str) -> str:
    """The ``--test`` distribution, ``test`` mapped to ``train`` with a deprecation line."""
    if name == "test":
        print(
            "taskvar eval: --test test is deprecated: it is the training distribution; use "
            "--test train",
            file=sys.stderr,
        )
        return "train"
    return name  # checked against the bundle's family by eval_bundle


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
    _overwrite_argument(p, "DIR (windy-fig2: DIR/train)")
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
    _set_threads(args)  # default 1: small MLPs, more threads only contend on a shared CPU
    config_path, overrides = _split_config_and_overrides(args.items)
    if args.checkpoint is not None:
        _check_checkpoint_overrides(overrides)
        if config_path is not None:  # its env/heads/train keys would be ignored
            raise ValueError(
                f"config file {config_path!r} cannot apply with --checkpoint: the bundle's own "
                "config is used; pass experiment.*, eval.* or device overrides instead"
            )
    cfg = exp.load_config(config_path or exp.default_config_path(), overrides, quick=args.quick)
    out = args.out or f"results/{args.name}{'-quick' if args.quick else ''}"
    exp.call(cfg, out, **options)
    return 0


CHECKPOINT_OVERRIDABLE = ("experiment", "eval", "device")
"""Config sections an override may change when ``experiment --checkpoint`` evaluates a bundle
(the rest comes from the bundle's own config)."""


def _check_checkpoint_overrides(overrides: Sequence[str]) -> None:
    """Refuse overrides that a ``--checkpoint`` run would ignore (e.g. ``env.layout=...``)."""
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if not any(key == k or key.startswith(k + ".") for k in CHECKPOINT_OVERRIDABLE):
            raise ValueError(
                f"override {item!r} cannot apply with --checkpoint: the bundle's own config is "
                f"used; only {', '.join(k + ('.*' if k != 'device' else '') for k in CHECKPOINT_OVERRIDABLE)} "
                "may be overridden (train a new bundle to change it)"
            )


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
    _overwrite_argument(p, "DIR (the sweep and its points)")
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
    for path in experiment_of_folder(args.results).plot_results(args.results):
        print(path)
    return 0


def _export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", metavar="PATH", help="a training checkpoint (final.pt)")
    p.add_argument(
        "--out", metavar="FILE", help="where to write it (default: heads.pt beside PATH)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")


def _export_run(args: argparse.Namespace) -> int:
    from taskvar_torch.factory import export_heads

    path = export_heads(args.checkpoint, args.out, overwrite=args.overwrite)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


# --------------------------------------------------------------------------------------------
# taskvar train-baselines (issue 31: docs/memory.md)


def _train_baselines_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "items",
        nargs="*",
        metavar="[CONFIG] [key.sub=value ...]",
        help="YAML config (default: DIR/config.yaml of the bundle in --out), then config "
        "overrides: the baselines read the heads' settings (heads.hidden, train.lr, "
        "train.total_frames ...) and the recurrent one its own baseline.hidden, "
        "baseline.slice_len and baseline.burn_in",
    )
    p.add_argument(
        "--out", required=True, metavar="DIR", help="bundle folder (beside final.pt) or a new one"
    )
    p.add_argument(
        "--method",
        default="all",
        help="recurrent, informed or all (default: recurrent, and informed where the family "
        "gives instance features and the heads did not train it with heads.informed)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace DIR/<method>.pt if it exists")
    _threads_argument(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _train_baselines_run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from taskvar_torch.config import load_config
    from taskvar_torch.heads.informed import informed_features
    from taskvar_torch.heads.recurrent import BASELINES, baseline_path
    from taskvar_torch.run_folder import check_output_folder
    from taskvar_torch.train_recurrent import heads_only_keys, train_baseline

    _set_threads(args)
    config_path, overrides = _split_config_and_overrides(list(args.items))
    if config_path is None:
        config_path = str(Path(args.out) / "config.yaml")
        if not Path(config_path).is_file():
            raise ValueError(f"give a CONFIG file: {args.out!r} holds no config.yaml")
    if args.method not in (*BASELINES, "all"):
        raise ValueError(f"--method must be one of {[*BASELINES, 'all']}, got {args.method!r}")
    check_output_folder(args.out)
    cfg = load_config(config_path, overrides)
    methods = list(BASELINES) if args.method == "all" else [args.method]
    if "informed" in methods:
        try:
            informed_features(cfg)
        except ValueError as e:
            if args.method != "all":
                raise
            print(f"taskvar train-baselines: skipping informed: {e}", file=sys.stderr)
            methods.remove("informed")
    if args.method == "all" and "informed" in methods and cfg.heads.informed:
        print(
            "taskvar train-baselines: skipping informed: the heads trained it (heads.informed); "
            "--method informed trains one apart",
            file=sys.stderr,
        )
        methods.remove("informed")
    for m in methods:
        dest = baseline_path(Path(args.out) / "final.pt", m)
        if dest.exists() and not args.overwrite:
            raise ValueError(f"{str(dest)!r} exists; pass --overwrite to replace it")
    heads_only = heads_only_keys(cfg)
    if heads_only:
        print(
            f"taskvar train-baselines: {', '.join(heads_only)} shape the heads' replay only; the "
            "baselines take one-step targets on uniform samples",
            file=sys.stderr,
        )
    for m in methods:
        r = train_baseline(cfg, m, args.out, progress=not args.no_progress)
        last = r["mean_train_return"]
        last_s = "no episode ended" if last != last else f"{last:.3f}"  # NaN: none ended
        print(
            f"trained {m}: {r['updates']} updates on {r['frames']} frames in {r['seconds']:.1f} s "
            f"(mean training return of the last tenth: {last_s}); wrote {r['path']}"
        )
    return 0


# --------------------------------------------------------------------------------------------
# taskvar report


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
        "<FILE stem>-results.json (the data of the README's compact tables) (required unless --add)",
    )
    p.add_argument(
        "--readme",
        metavar="FILE",
        help="also replace the Results block between <!-- report:results:start --> and "
        "<!-- report:results:end --> in FILE (README.md): the regret figure, per family a compact "
        "table (methods as columns, the winner bold) and the table of every result, folded",
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
        help="only add these folders' rows to the --readme Results table (a row of the same "
        "experiment and config is replaced, the others kept) and write no claims page; for "
        "results that score none of the paper's claims (--out: the page the rows link to, "
        "default docs/claims.md beside the README)",
    )


def _report_run(args: argparse.Namespace) -> int:
    from taskvar_torch.study.report import CLAIMS, ReportError, add_rows, write_report

    if args.add:
        if args.readme is None:
            raise ReportError("--add needs --readme FILE: the README whose Results table grows")
        written, _ = add_rows(args.dirs, args.readme, args.out, args.reps)
        print("wrote " + ", ".join(str(p) for p in written))
        return 0
    if args.out is None:
        raise ReportError("--out FILE is required (the claims page, docs/claims.md) unless --add")
    written, report = write_report(args.dirs, args.out, args.readme, args.reps, args.overwrite)
    for c in report.claims:
        print(f"{CLAIMS[c.key][0]} [{c.group}]: {c.verdict} ({c.reason})")
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


# --------------------------------------------------------------------------------------------
# registry and entry point

COMMANDS: dict[str, Command] = {
    "train": Command(
        help="train every head (averaging, options, mu_bar, max-value, robustness)",
        description="Train every head of a family from one stream of experience: "
        "CSV logs in DIR/logs, periodic checkpoints, DIR/final.pt.",
        add_arguments=_train_arguments,
        run=_train_run,
        epilog=_train_epilog,
    ),
    "eval": Command(
        help="evaluate a trained bundle's methods side by side on test distributions and shifts",
        description="Evaluate any saved bundle of either family without retraining: every method "
        "on the same paired episodes of a named test distribution, optionally shifted "
        "(--shift env.KEY=V, or V1,V2,... for a shift curve); prints a table and writes "
        "DIR/metrics.json, episodes.csv and eval.png with --out.\n\n"
        "  taskvar eval --checkpoint runs/windy/final.pt --method all --shift env.instances.p=0.2,0.5,0.8",
        add_arguments=_eval_arguments,
        run=_eval_run,
    ),
    "train-baselines": Command(
        help="train the recurrent and informed baselines beside a bundle (docs/memory.md)",
        description="Train a recurrent Q-network (TorchRL GRUModule, SliceSampler, double DQN) and "
        "an instance-informed Q-network (the learnt ceiling) with the config's frame budget, "
        "written as DIR/recurrent.pt and DIR/informed.pt; taskvar eval --method all plays them "
        "beside the paper's methods.\n\n"
        "  taskvar train-baselines configs/windy.yaml --out runs/windy --method all",
        add_arguments=_train_baselines_arguments,
        run=_train_baselines_run,
    ),
    "experiment": Command(
        help="run one of the paper's experiments (windy-fig2, wargus-fig4, scale)",
        description="Train (or load --checkpoint), evaluate, write a results folder and print a "
        "table.",
        add_arguments=_experiment_arguments,
        run=_experiment_run,
    ),
    "sweep": Command(
        help="run an experiment over a grid of config overrides (local or Ray)",
        description="Run the config family's experiment (windy-fig2 or wargus-fig4) once per "
        "point of the Cartesian product of key=v1,v2 values, locally or as Ray tasks; print and "
        "write a summary table (DIR/summary.csv, DIR/summary.json).\n\n"
        "  taskvar sweep configs/windy.yaml --backend ray --quick --out results/sweep seed=0,1",
        add_arguments=_sweep_arguments,
        run=_sweep_run,
    ),
    "export": Command(
        help="write a checkpoint's shareable bundle (heads and config, no replay or optimiser)",
        description="Write the evaluation bundle of a training checkpoint: the heads, their "
        "constructor arguments and the config (taskvar train writes it as DIR/heads.pt).",
        add_arguments=_export_arguments,
        run=_export_run,
    ),
    "plot": Command(
        help="redraw the figures of an experiment's results folder",
        description="(Re)draw the PNG figures of a results folder.",
        add_arguments=_plot_arguments,
        run=_plot_run,
    ),
    "report": Command(
        help="regenerate the paper's claims page and the README's Results table from results",
        description="Read results folders (many training seeds), aggregate them with rliable on "
        "the sealed held-out instances and write the claims page (the paper's figure, ours with "
        "its 95% CI, a verdict), its performance profiles and, with --readme, the README's "
        "Results table (docs/report.md).\n\n"
        "  taskvar report results/fig2-seeds results/fig4 --out docs/claims.md --readme README.md",
        add_arguments=_report_arguments,
        run=_report_run,
    ),
}
"""Subcommands by name; add an entry to add a command."""


class _OneLineParser(argparse.ArgumentParser):
    """``argparse`` whose input errors are one line ``PROG: error: ...`` (no usage block), status 2."""

    def error(self, message: str):  # argparse API
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The ``taskvar`` parser and one parser per subcommand."""
    parser = _OneLineParser(
        prog="taskvar",
        description="Offline learning across task variations for online performance "
        "(averaging policy, offline options, offline interruption, composition hierarchies).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    parsers = {}
    for name, cmd in COMMANDS.items():
        parsers[name] = sub.add_parser(
            name,
            help=cmd.help,
            description=cmd.description,
            epilog=cmd.epilog() if cmd.epilog else None,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        cmd.add_arguments(parsers[name])
    return parser, parsers


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``taskvar`` console script; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, parsers = build_parser()
    if not argv or argv[0] not in parsers:
        parser.parse_args(argv)  # --help, or an error naming the valid commands
        return 2
    name = argv[0]
    args = parsers[name].parse_intermixed_args(argv[1:])
    _quiet_third_party()
    with _TerminateAsInterrupt():
        return _run(name, args)


def _run(name: str, args: argparse.Namespace) -> int:
    """Run command ``name``; every failure is one line on stderr and an exit status: 2 for input
    (a value, a file, a folder, memory), 128 + N for signal N, 1 with the traceback for a bug."""
    try:
        if getattr(args, "out", None) is not None:  # --out '' would be the current folder
            check_out_path(args.out)
        return COMMANDS[name].run(args)
    except (ValueError, CheckpointError, RuntimeError) as e:
        if type(e).__name__ == "TrainingInterrupted":
            print(f"taskvar {name}: {e}", file=sys.stderr)
            return 128 + int(e.signum)
        if isinstance(e, RuntimeError) and type(e).__name__ != "TrainingDiverged":
            if _out_of_memory(e):
                return _memory_error(name)
            return _bug(name, e)
        print(f"taskvar {name}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a folder or file the command cannot write or read
        where = f" {e.filename!r}" if e.filename else ""
        print(f"taskvar {name}: error: cannot use{where}: {e.strerror or e}", file=sys.stderr)
        return 2
    except MemoryError:
        return _memory_error(name)
    except KeyboardInterrupt as e:
        signum = getattr(e, "signum", signal.SIGINT)
        text = f": {e}" if str(e) else f" by {signal.Signals(signum).name}"
        print(f"taskvar {name}: interrupted{text}", file=sys.stderr)
        return 128 + signum
    except Exception as e:  # not the input's fault: a bug, reported as one
        return _bug(name, e)


def _out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` is torch's out-of-memory error (CUDA's, or the CPU allocator's)."""
    import torch

    text = str(e).lower()
    return isinstance(e, torch.OutOfMemoryError) or any(
        marker in text for marker in ("out of memory", "can't allocate memory")
    )


def _memory_error(name: str) -> int:
    """The one line of an allocation that failed although the memory estimate let it pass."""
    print(
        f"taskvar {name}: error: out of memory: lower the sizes (env.num_envs, "
        "train.buffer_size, heads.hidden, eval.batch_size, --episodes)",
        file=sys.stderr,
    )
    return 2


def _bug(name: str, e: BaseException) -> int:
    """A failure that no input explains: the traceback, then one line saying it is a bug."""
    import traceback

    from taskvar_torch import __version__

    traceback.print_exception(e)
    print(
        f"taskvar {name}: internal error ({type(e).__name__}): this is a bug in taskvar_torch "
        f"{__version__}, not in your input; please report it to the taskvar_torch issue tracker "
        "with the command line and the traceback above",
        file=sys.stderr,
    )
    return 1


class _Terminated(KeyboardInterrupt):
    """SIGTERM outside the training loop (which handles its own): unwinds like Ctrl-C, so a run
    folder taken but not yet used is released and removed, and the command prints one line."""

    signum = signal.SIGTERM


class _TerminateAsInterrupt:
    """While a command runs in the main thread with the default SIGTERM handler, SIGTERM raises
    :class:`_Terminated`; the previous handler is restored after."""

    def __enter__(self) -> _TerminateAsInterrupt:
        self._old = None
        if threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
                self._old = signal.signal(signal.SIGTERM, self._raise)
        return self

    @staticmethod
    def _raise(signum: int, frame: object) -> None:
        raise _Terminated

    def __exit__(self, *exc: object) -> None:
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)


def _quiet_third_party() -> None:
    """TorchRL's INFO lines (e.g. "Initialized LazyTensorStorage") are not for this CLI's users;
    ``RL_LOGGING_LEVEL`` set in the environment still wins."""
    if "RL_LOGGING_LEVEL" not in os.environ:
        os.environ["RL_LOGGING_LEVEL"] = "WARNING"  # read when torchrl is first imported
        logging.getLogger("torchrl").setLevel(logging.WARNING)  # in case it already was


if __name__ == "__main__":
    sys.exit(main())
