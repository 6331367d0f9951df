"""Scaling with collector processes and batch size (docs/benchmarks.md, Collector workers).

(a) env steps/s: ``WindyGridEnv`` stepped by the trainer's collector (:func:`make_collector`,
    the real behaviour policy, epsilon 0.1), ``--steps`` steps per sub-env per batch, the weight
    sync after every batch included (W > 1), process start-up excluded;
(b) training frames/s: the real :func:`train` on ``--batches`` + 1 batches of ``4 N`` frames (the
    first one random, then ``--updates`` gradient steps per batch), timed from the end of the first
    batch (process start-up and first batch printed apart).

Both against the number of collector processes W (``collector.num_workers``) and the number of
environments N (``env.num_envs``, split evenly between the W processes), with the ratio of each W
to one process at the same N. Every process runs ``--threads`` torch threads (default 1).
``--backend ray`` runs the W workers as Ray actors on a local Ray (``collector.backend=ray``; W = 1
is then one actor, not the trainer's own process); ``--backend process,ray`` measures both, one
after the other, and adds the ratio ray / process for each (N, W).

Usage: ``python benchmarks/scale.py [--workers 1,2] [--sizes 256,4096,16384] [--threads 1]
[--device cpu] [--backend process|ray|process,ray] [--quick]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, make_subtasks
from taskvar_torch.heads.behaviour import BehaviourPolicy
from taskvar_torch.training import train
from taskvar_torch.training.collection import collects_in_workers, make_collector, make_training_env

CONFIG = "configs/windy.yaml"


def sync(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def bench_collect(n_envs: int, workers: int, steps: int, batches: int, device: str, backend: str):
    """(env steps/s, start-up seconds) of the trainer's collector."""
    cfg = load_config(
        CONFIG,
        [
            f"env.num_envs={n_envs}",
            f"train.frames_per_batch={n_envs * steps}",
            f"collector.num_workers={workers}",
            f"collector.backend={backend}",
            f"device={device}",
        ],
    )
    t0 = time.perf_counter()
    torch.manual_seed(cfg.seed)
    env = make_training_env(cfg, num_envs=n_envs // workers)
    subtasks = make_subtasks(cfg, env.base_env)
    heads = build_heads(cfg, env, subtasks)
    behaviour = BehaviourPolicy(
        heads, subtasks, env.action_spec, option_prob=cfg.train.option_behaviour_prob, eps=0.1
    )
    collector = make_collector(cfg, env, behaviour, total_frames=-1)
    it = iter(collector)
    next(it)  # warm-up batch
    sync(device)
    startup = time.perf_counter() - t0
    frames, t0 = 0, time.perf_counter()
    for _ in range(batches):
        frames += next(it).numel()
        if collects_in_workers(cfg):
            collector.update_policy_weights_(behaviour)
    sync(device)
    rate = frames / (time.perf_counter() - t0)
    threads = torch.get_num_threads()
    collector.shutdown()
    torch.set_num_threads(threads)  # MultiSyncCollector.shutdown adds num_workers threads
    return rate, startup


def bench_train(n_envs: int, workers: int, batches: int, updates: int, device: str, backend: str):
    """(training frames/s, start-up seconds) of :func:`train` on a small budget.

    The rate runs from the end of the first batch to the end of the last (``train`` logs a row
    with its elapsed seconds after every batch); start-up is the rest of the wall time.
    """
    fpb = 4 * n_envs
    cfg = load_config(
        CONFIG,
        [
            f"env.num_envs={n_envs}",
            f"train.frames_per_batch={fpb}",
            f"train.total_frames={fpb * (batches + 1)}",
            f"train.init_random_frames={fpb}",
            f"train.eps_decay_frames={fpb * batches}",
            f"train.updates_per_batch={updates}",
            f"train.buffer_size={fpb * (batches + 1)}",
            "train.checkpoint_every=0",
            f"train.log_every={fpb}",
            f"collector.num_workers={workers}",
            f"collector.backend={backend}",
            f"device={device}",
        ],
    )
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        train(cfg, out, progress=False)
        sync(device)
        wall = time.perf_counter() - t0
        rows = (Path(out) / "logs" / "scalars" / "seconds.csv").read_text().split()
    (f0, s0), (f1, s1) = [[float(x) for x in row.split(",")] for row in (rows[0], rows[-1])]
    return (f1 - f0) / (s1 - s0), wall - (s1 - s0)


def table(title: str, rows: dict[tuple[int, int], tuple[float, float]]) -> None:
    """One row per N: for each W, the rate, its ratio to W=1 and the start-up seconds."""
    sizes = sorted({n for n, _ in rows})
    workers = sorted({w for _, w in rows})
    print(f"\n{title}")
    print(f"{'N':>6} | " + " | ".join(f"W={w}: rate/s (x W=1), start s" for w in workers))
    for n in sizes:
        base = rows[(n, workers[0])][0]
        cells = [
            f"{r / 1e3:9.1f}k ({r / base:4.2f}x), {s:5.1f}"
            for r, s in (rows[(n, w)] for w in workers)
        ]
        print(f"{n:>6} | " + " | ".join(f"{c:>29}" for c in cells))


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--workers", default=None, help="collector process counts W (default 1,2; --quick: 1)"
    )
    ap.add_argument("--sizes", default="256,4096,16384", help="env.num_envs values N")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per process")
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--backend",
        default="process",
        help="collector.backend: process, ray (local Ray actors) or process,ray (both)",
    )
    ap.add_argument("--steps", type=int, default=16, help="(a) steps per sub-env per batch")
    ap.add_argument("--batches", type=int, default=5, help="timed batches, (a) and (b)")
    ap.add_argument("--updates", type=int, default=8, help="(b) gradient steps per batch")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="N=64, W=1 (unless --workers is given), 2 batches (smoke run)",
    )
    args = ap.parse_args()
    if args.quick:
        args.sizes, args.batches, args.steps = "64", 2, 4
    # W > 1 starts processes (~15 s each on this machine): --quick runs W=1 unless told
    args.workers = args.workers or ("1" if args.quick else "1,2")
    torch.set_num_threads(args.threads)
    workers = [int(w) for w in args.workers.split(",")]
    sizes = [int(n) for n in args.sizes.split(",")]
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} thread(s) per process, "
        f"device={args.device}, windy default layout"
    )
    backends = args.backend.split(",")
    for b in backends:
        if b not in ("process", "ray"):
            raise SystemExit(f"--backend: each of {backends} must be process or ray")
    collect, learn = {}, {}
    for b in backends:
        collect[b], learn[b] = {}, {}
        for n in sizes:
            for w in workers:
                collect[b][(n, w)] = bench_collect(n, w, args.steps, args.batches, args.device, b)
                learn[b][(n, w)] = bench_train(n, w, args.batches, args.updates, args.device, b)
                print(
                    f"  {b} N={n} W={w}: {collect[b][(n, w)][0] / 1e3:.1f}k env steps/s, "
                    f"{learn[b][(n, w)][0] / 1e3:.1f}k training frames/s",
                    flush=True,
                )
    for b in backends:
        table(
            f"[{b}] (a) env steps/s through the collector ({args.steps} steps per batch)",
            collect[b],
        )
        table(
            f"[{b}] (b) training frames/s, train() ({args.updates} updates per batch of 4N frames)",
            learn[b],
        )
    if len(backends) == 2:
        print("\nray / process, same N and W: (a) env steps/s, (b) training frames/s")
        for n in sizes:
            for w in workers:
                ra = collect["ray"][(n, w)][0] / collect["process"][(n, w)][0]
                rb = learn["ray"][(n, w)][0] / learn["process"][(n, w)][0]
                print(f"  N={n:>6} W={w}: (a) {ra:4.2f}x  (b) {rb:4.2f}x")


if __name__ == "__main__":
    main()
