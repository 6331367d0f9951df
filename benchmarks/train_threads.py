"""Training on one torch thread and on two, side by side in one run (docs/benchmarks.md).

The real :func:`~taskvar_torch.training.train` of a family config (default ``configs/windy_xl.yaml``,
the 51x51 family, cut to ``--frames``) with ``torch.set_num_threads(1)`` and with ``2``, in
alternating rounds (1, 2, 1, 2, ...) so that machine load hits both alike. Prints each run's
training seconds (the trainer's own clock), the median ratio, and whether the two thread counts
trained the same heads bit for bit (the learner's matrix products split over rows and columns,
not over the sums, on the CPUs measured so far; the check says so for this one).

Usage::

    python benchmarks/train_threads.py [--config configs/windy_xl.yaml] [--frames 300000]
        [--rounds 2] [--threads 1,2] [--quick] [overrides ...]

Only meaningful with the cores otherwise idle: a second thread on a busy core only contends.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile

import torch

from taskvar_torch.checkpoint import load_checkpoint
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


def run(cfg, threads: int) -> tuple[float, dict[str, torch.Tensor]]:
    """Train ``cfg`` on ``threads`` torch threads; its training seconds and final heads."""
    torch.set_num_threads(threads)
    with tempfile.TemporaryDirectory() as out:
        result = train(cfg, out, progress=False)
        heads = load_checkpoint(result["final"])["models"]["heads"]
    return result["seconds"], heads


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/windy_xl.yaml")
    p.add_argument("--frames", type=int, default=300_000, help="train.total_frames of each run")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--threads", default="1,2", help="thread counts, the first is the baseline")
    p.add_argument(
        "--quick", action="store_true", help="5x5 windy.yaml, 2k frames, 1 round (smoke run)"
    )
    p.add_argument("overrides", nargs="*")
    args = p.parse_args()
    extra = []
    if args.quick:
        args.config, args.frames, args.rounds, extra = "configs/windy.yaml", 2048, 1, QUICK
    counts = [int(t) for t in args.threads.split(",")]
    cfg = load_config(args.config, [f"train.total_frames={args.frames}", *extra, *args.overrides])
    seconds: dict[int, list[float]] = {t: [] for t in counts}
    heads: dict[int, dict[str, torch.Tensor]] = {}
    for r in range(args.rounds):
        for t in counts:
            s, heads[t] = run(cfg, t)
            seconds[t].append(s)
            print(f"round {r}: {t} thread(s) {s:7.1f} s training", flush=True)
    base = counts[0]
    print(
        f"{args.config}, {args.frames} frames, median training seconds over {args.rounds} rounds:"
    )
    for t in counts:
        same = all(torch.equal(heads[t][k], heads[base][k]) for k in heads[base])
        ratio = statistics.median(seconds[base]) / statistics.median(seconds[t])
        print(
            f"  {t} thread(s): {statistics.median(seconds[t]):7.1f} s, {ratio:.2f}x over "
            f"{base}; heads {'bit-equal' if same else 'DIFFER'} to {base} thread(s)"
        )


if __name__ == "__main__":
    main()
