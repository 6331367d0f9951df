"""``taskvar eval``: any saved bundle's methods side by side on paired episodes of a test
distribution, optionally shifted (docs/evaluation.md)."""

from __future__ import annotations

import argparse
import sys

from taskvar_torch.cli.arguments import Command, overwrite_argument, set_threads, threads_argument


def _eval_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "settings",
        nargs="*",
        metavar="train.KEY=VALUE",
        help="controller settings to play instead of the bundle's, without retraining (e.g. "
        "train.robustness_threshold=fixed train.robustness_tau=1.5); the keys: below",
    )
    p.add_argument(
        "--checkpoint",
        required=True,
        metavar="PATH",
        help="bundle of any family: taskvar train's final.pt, an experiment repetition's, or an "
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
        help="named test distribution of the bundle's family (each registered family's: below; "
        "heldout: the sealed held-out episodes; docs/evaluation.md); default: the family's first",
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
    overwrite_argument(p, "DIR")
    threads_argument(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _eval_run(args: argparse.Namespace) -> int:
    from taskvar_torch.config.controller import check_controller_overrides
    from taskvar_torch.experiments.bundle_eval import eval_bundle, format_table
    from taskvar_torch.experiments.explain import explain_table
    from taskvar_torch.experiments.regret_frames import format_by_frames
    from taskvar_torch.experiments.shift import parse_shift

    set_threads(args)
    test = None if args.test is None else _test_name(args.test)
    shifts = [parse_shift(s) for s in args.shift]  # one-line errors before any loading
    check_controller_overrides(args.settings)
    if args.batch_size is not None and args.batch_size < 1:  # 0 would fall back to the config's
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
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
        controller=args.settings,
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


def _tests_epilog() -> str:
    """``taskvar eval --help``'s epilog: each registered family's named tests (``--test``) and
    the controller settings an evaluation may change, with their help."""
    from taskvar_torch.config import Config
    from taskvar_torch.config.controller import CONTROLLER_KEYS
    from taskvar_torch.config.help import key_line, unloaded_plugin
    from taskvar_torch.contract import FAMILIES

    lines = ["--test, per registered family (the first is the default):"]
    for name, fam in FAMILIES.loaded().items():
        lines.append(f"  {name}: {', '.join(fam.tests)}")
    for name, value in sorted(FAMILIES.entry_points().items()):
        lines.append(f"  {name}: {unloaded_plugin(name, value)}")
    lines.append("\ncontroller settings (train.KEY=VALUE; the bundle's own by default):")
    lines += [key_line(Config, key) for key in CONTROLLER_KEYS]
    return "\n".join(lines)


EVAL = Command(
    help="evaluate a trained bundle's methods side by side on test distributions and shifts",
    description="Evaluate any saved bundle of any family without retraining: every method "
    "on the same paired episodes of a named test distribution, optionally shifted "
    "(--shift env.KEY=V, or V1,V2,... for a shift curve); prints a table and writes "
    "DIR/metrics.json, episodes.csv and eval.png with --out. Controller settings "
    "(train.KEY=VALUE, listed below) change what the controllers do with the same heads.\n\n"
    "  taskvar eval --checkpoint runs/windy/final.pt --method all --shift env.instances.p=0.2,0.5,0.8\n"
    "  taskvar eval --checkpoint runs/wargus/final.pt --method hierarchy "
    "train.robustness_threshold=fixed",
    add_arguments=_eval_arguments,
    run=_eval_run,
    epilog=_tests_epilog,
)
