"""Training throughput of config variants, side by side in one run (docs/scale.md).

The real :func:`~taskvar_torch.training.train` of a family config (default ``configs/windy_xxl.yaml``,
the 101x101 family, cut to ``--frames``) for each variant (``NAME=key.sub=value,...``; the first
is the baseline), in alternating rounds (A, B, A, B, ...) so that machine load hits every variant
alike. The rate is read from the run's own log rows (``logs/scalars/seconds.csv``) from the
second row on, so it leaves out the start-up and, with ``train.compile``, most of the compile.
Prints each run's frames per second, then each variant's median rate and its ratio to the
baseline's.

Usage::

    python benchmarks/train_variants.py --threads 2 \\
        --variant eager= --variant compiled=train.compile=true
    python benchmarks/train_variants.py --threads 2 \\
        --variant 16x256= --variant 8x512=train.batch_size=512,train.updates_per_batch=8
    python benchmarks/train_variants.py --quick   # a smoke run: 5x5 layout, 2k frames, one variant

The variants change what is learnt (except where they only change speed): this measures speed
only; ``benchmarks/time_to_bundle.py`` measures the heads.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import tempfile
from pathlib import Path

import torch
from time_to_bundle import parse_variant  # benchmarks/ is the script's folder on sys.path

from taskvar_torch.config import load_config
from taskvar_torch.training import train

# --quick: the 5x5 family, a few hundred updates (a smoke run)
QUICK = [
    "train.init_random_frames=512",
    "train.eps_decay_frames=1024",
    "train.updates_per_batch=4",
    "train.checkpoint_every=0",
    "train.log_every=256",
]


def steady_rate(config: str, overrides: list[str]) -> tuple[float, int]:
    """Train in a scratch folder; frames per second between its first and last log rows, and the
    frames between them."""
    cfg = load_config(config, [*overrides, "train.checkpoint_every=0"])
    with tempfile.TemporaryDirectory() as tmp:
        train(cfg, Path(tmp) / "run", progress=False, keep_replay=False)
        with open(Path(tmp) / "run" / "logs" / "scalars" / "seconds.csv") as f:
            rows = [(int(frames), float(s)) for frames, s in csv.reader(f)]
    if len(rows) < 3:
        raise SystemExit("too few log rows: raise --frames or lower train.log_every")
    (f0, s0), (f1, s1) = rows[1], rows[-1]
    return (f1 - f0) / (s1 - s0), f1 - f0


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/windy_xxl.yaml")
    ap.add_argument("--frames", type=int, default=600_000, help="train.total_frames of each run")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    ap.add_argument(
        "--variant",
        action="append",
        type=parse_variant,
        help="NAME=key.sub=value,... (repeatable; the first is the baseline)",
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help="5x5 windy.yaml, 2k frames, 1 round, variant base= unless given (smoke run)",
    )
    args = ap.parse_args(argv)
    extra = []
    if args.quick:
        args.config, args.frames, args.rounds, extra = "configs/windy.yaml", 2048, 1, QUICK
        args.variant = args.variant or [("base", [])]
    if not args.variant:
        ap.error("--variant is required (or --quick)")
    torch.set_num_threads(args.threads)
    rates: dict[str, list[float]] = {name: [] for name, _ in args.variant}
    for r in range(args.rounds):
        for name, overrides in args.variant:
            rate, frames = steady_rate(
                args.config, [f"train.total_frames={args.frames}", *extra, *overrides]
            )
            rates[name].append(rate)
            print(f"round {r}: {name:<12} {rate:8.0f} frames/s over {frames} frames", flush=True)
    base = statistics.median(rates[args.variant[0][0]])
    print(f"{args.config}, {args.frames} frames, {args.threads} thread(s), {args.rounds} rounds:")
    for name, values in rates.items():
        med = statistics.median(values)
        print(f"  {name:<12} median {med:8.0f} frames/s, x{med / base:.2f} of {args.variant[0][0]}")


if __name__ == "__main__":
    main()
