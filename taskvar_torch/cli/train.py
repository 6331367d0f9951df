"""``taskvar train``, ``taskvar train-baselines`` and ``taskvar export``: training the heads, the
baselines beside them, and writing a bundle's shareable heads."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from taskvar_torch.cli.arguments import (
    Command,
    overwrite_argument,
    set_threads,
    split_config_and_overrides,
    threads_argument,
)

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
    overwrite_argument(p, "DIR")
    threads_argument(p)
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
    from taskvar_torch.config.help import config_help, count_keys, families_help, user_help

    return (
        "the config keys a user sets (override any key with key.sub=value):\n"
        + user_help()
        + "\n\nthe registered families (family=NAME; installed packages' included):\n"
        + families_help()
        + f"\n\ntaskvar train --help-all lists every key ({count_keys(config_help())}), "
        "grouped by section, with each family's own"
    )


class _HelpAll(argparse.Action):
    """``--help-all``: every config key, grouped by section, with each family's own; exits."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *args: Any, **kwargs: Any) -> None:
        from taskvar_torch.config.help import config_help, families_help

        print(
            "every config key (override any with key.sub=value):\n"
            + config_help()
            + "\n\nthe registered families (family=NAME):\n"
            + families_help()
        )
        parser.exit()


def _train_run(args: argparse.Namespace) -> int:
    from taskvar_torch.config import load_config
    from taskvar_torch.training import train

    set_threads(args)
    config_path, overrides = split_config_and_overrides(args.items)
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
    from taskvar_torch.contract import family
    from taskvar_torch.factory import load_heads

    heads, cfg = load_heads(path)
    summary = family(cfg).oracle_summary
    for line in summary(heads, cfg) if summary is not None else []:
        print(line)


# --------------------------------------------------------------------------------------------
# taskvar train-baselines (docs/memory.md)


def _train_baselines_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "items",
        nargs="*",
        metavar="[CONFIG] [key.sub=value ...]",
        help="YAML config (default: DIR/config.yaml of the bundle in --out), then config "
        "overrides: the baselines read the heads' settings (heads.hidden, train.lr, "
        "train.total_frames, train.n_step ...) and their own baseline.* keys (the recurrent "
        "one's baseline.hidden, baseline.slice_len, baseline.burn_in, baseline.recurrent_frames; "
        "informed's and blind's baseline.informed_frames, baseline.informed_ema_tau)",
    )
    p.add_argument(
        "--out", required=True, metavar="DIR", help="bundle folder (beside final.pt) or a new one"
    )
    p.add_argument(
        "--method",
        default="all",
        help="recurrent, informed, blind or all (default: recurrent, and informed and blind "
        "where the family gives instance features)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace DIR/<method>.pt if it exists")
    threads_argument(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _train_baselines_run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from taskvar_torch.config import load_config
    from taskvar_torch.heads.informed import informed_features
    from taskvar_torch.heads.recurrent import BASELINES, baseline_path
    from taskvar_torch.run_folder import ResultsFolder, check_output_folder
    from taskvar_torch.training.baselines import heads_only_keys, train_baseline
    from taskvar_torch.training.run_state import seed_config

    set_threads(args)
    config_path, overrides = split_config_and_overrides(list(args.items))
    if config_path is None:
        config_path = str(Path(args.out) / "config.yaml")
        if not Path(config_path).is_file():
            raise ValueError(f"give a CONFIG file: {args.out!r} holds no config.yaml")
    if args.method not in (*BASELINES, "all"):
        raise ValueError(f"--method must be one of {[*BASELINES, 'all']}, got {args.method!r}")
    check_output_folder(args.out)
    cfg = load_config(config_path, overrides)
    _check_bundle_config(cfg, Path(args.out), overrides)
    methods = list(BASELINES) if args.method == "all" else [args.method]
    if "informed" in methods or "blind" in methods:  # blind: the same network, features zeroed
        try:
            informed_features(cfg)
        except ValueError as e:
            if args.method != "all":
                raise
            print(f"taskvar train-baselines: skipping informed and blind: {e}", file=sys.stderr)
            methods = [m for m in methods if m not in ("informed", "blind")]
    out = Path(args.out)
    runs = [(out, cfg)]
    if cfg.train.seeds > 1:  # a --seeds batch: a baseline beside every seed's bundle
        runs = [(out / f"seed{k}", seed_config(cfg, k)) for k in range(cfg.train.seeds)]
        for folder, cfg_k in runs:
            _check_bundle_config(cfg_k, folder, overrides)
    for m in methods:  # nothing is trained if any would be replaced unasked
        for folder, _ in runs:
            dest = baseline_path(folder / "final.pt", m)
            if dest.exists() and not args.overwrite:
                raise ValueError(f"{str(dest)!r} exists; pass --overwrite to replace it")
    heads_only = heads_only_keys(cfg, methods)
    if heads_only:
        print(
            f"taskvar train-baselines: {', '.join(heads_only)} not used: the recurrent "
            "baseline takes one-step targets on its slices, every baseline samples uniformly",
            file=sys.stderr,
        )
    for i, (folder, cfg_k) in enumerate(runs):
        if len(runs) > 1:
            print(f"seed {cfg_k.seed} ({i + 1}/{len(runs)} of train.seeds): {folder}", flush=True)
        with ResultsFolder(folder, staged=False):  # one writer at a time
            for m in methods:
                r = train_baseline(cfg_k, m, folder, progress=not args.no_progress)
                last = r["mean_train_return"]
                last_s = "no episode ended" if last != last else f"{last:.3f}"  # NaN: none ended
                print(
                    f"trained {m}: {r['updates']} updates on {r['frames']} frames in "
                    f"{r['seconds']:.1f} s (mean training return of the last tenth: {last_s}); "
                    f"wrote {r['path']}"
                )
    return 0


def _check_bundle_config(cfg: Any, out: Path, overrides: Sequence[str]) -> None:
    """A one-line ``ValueError`` when ``out`` holds a bundle whose family, environment or heads
    differ from ``cfg``'s (a ``heads.*`` override on the command line sets the baselines' width).
    """
    from taskvar_torch.config import config_to_dict, load_config

    saved = out / "config.yaml"
    if not saved.is_file():
        return
    mine, theirs = config_to_dict(cfg), config_to_dict(load_config(saved))
    if mine["family"] != theirs["family"]:
        raise ValueError(
            f"the config's family {mine['family']!r} differs from the bundle's "
            f"{theirs['family']!r} in --out {str(out)!r}; give the bundle's config (or none: "
            f"{str(saved)!r} is read) or another --out"
        )
    set_here = [o.partition("=")[0].strip() for o in overrides]
    for section in ("env", "heads"):
        for key, value, other in _differences(mine[section], theirs[section], section):
            if key in ("env.num_envs",) or (
                section == "heads" and any(key == s or key.startswith(s + ".") for s in set_here)
            ):
                continue
            raise ValueError(
                f"the config's {key}={value!r} differs from the bundle's {other!r} in --out "
                f"{str(out)!r}; give the bundle's config (or none: {str(saved)!r} is read), "
                f"override {key} on the command line, or choose another --out"
                if section == "heads"
                else f"the config's {key}={value!r} differs from the bundle's {other!r} in --out "
                f"{str(out)!r}; give the bundle's config (or none: {str(saved)!r} is read) or "
                "another --out"
            )


def _differences(a: Any, b: Any, prefix: str) -> Iterator[tuple[str, Any, Any]]:
    """``(dotted key, a's value, b's value)`` where two plain config dicts differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            yield from _differences(a.get(k), b.get(k), f"{prefix}.{k}")
    elif a != b:
        yield prefix, a, b


# --------------------------------------------------------------------------------------------
# taskvar export


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


TRAIN = Command(
    help="train every head (averaging, options, mu_bar, max-value, robustness)",
    description="Train every head of a family from one stream of experience: "
    "CSV logs in DIR/logs, periodic checkpoints, DIR/final.pt.",
    add_arguments=_train_arguments,
    run=_train_run,
    epilog=_train_epilog,
)


TRAIN_BASELINES = Command(
    help="train the recurrent, informed and blind baselines beside a bundle (docs/memory.md)",
    description="Train the baselines, each a DQN agent on its own epsilon-greedy stream with the "
    "heads' width, target settings and frame budget: a recurrent Q-network (TorchRL GRUModule, "
    "SliceSampler), an instance-informed Q-network (the learnt ceiling, where a validation run "
    "shows it is one) and blind (the same network, the instance features zeroed); written as "
    "DIR/recurrent.pt, DIR/informed.pt and DIR/blind.pt; taskvar eval --method all plays them "
    "beside the paper's methods.\n\n"
    "  taskvar train-baselines configs/windy.yaml --out runs/windy --method all",
    add_arguments=_train_baselines_arguments,
    run=_train_baselines_run,
)


EXPORT = Command(
    help="write a checkpoint's shareable bundle (heads and config, no replay or optimiser)",
    description="Write the evaluation bundle of a training checkpoint: the heads, their "
    "constructor arguments and the config (taskvar train writes it as DIR/heads.pt).",
    add_arguments=_export_arguments,
    run=_export_run,
)
