"""Env throughput, measured side by side in one run (docs/benchmarks.md).

(a) a Gymnasium loop over ``taskvar/WindyGrid-v0``;
(b) the raw batched windy step (keyed wind draw + dynamics + step counter) at several N;
(c) ``WindyGridEnv`` driven by TorchRL's ``Collector`` with a random policy at N=16384, three ways:
    c0: the collector as first measured (``TensorDictModule`` policy, trajectory ids, a fresh batch
        every iteration);
    c1: the improved collector: a ``TensorDictModuleBase`` policy (no ``TensorDictModule`` output
        wrapping), ``track_traj_ids=False``, ``return_same_td=True`` (the batch's memory reused);
    c2: the fast path ``rollout_fast`` (benchmarks/reference/windy_fast_rollout.py) (same batch layout and values as the
        collector, tested), writing into the previous batch (``out=``).
    All use ``compact_obs=True`` and 16 steps per batch.

Usage: ``python benchmarks/env_throughput.py [--threads 1,2] [--device cpu] [--quick]``.
Prints steps/s and the ratios b/a, c/b and c1/c0, c2/c0 for each thread count.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.collectors import Collector

import taskvar_torch  # noqa: F401
from taskvar_torch import rng
from taskvar_torch.families.windy import WindyGridEnv, WindyLayout, WindyModel
from taskvar_torch.families.windy import dynamics as windy

sys.path.insert(0, str(Path(__file__).resolve().parent / "reference"))
from windy_fast_rollout import rollout_fast  # noqa: E402  (the reference loop, path c2)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def bench_gym(seconds: float) -> float:
    env = gym.make("taskvar/WindyGrid-v0")
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 4, 1_000_000)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(2000):
            _, _, term, trunc, _ = env.step(int(actions[n % len(actions)]))
            n += 1
            if term or trunc:
                env.reset()
    return n / (time.perf_counter() - t0)


def bench_raw(n_envs: int, seconds: float, device: torch.device) -> float:
    model = WindyModel(WindyLayout.named("default"), device)
    key = rng.to_i32(rng.sub_env_key(0, torch.arange(n_envs, device=device)))
    cell = model.start_cells[torch.arange(n_envs, device=device) % 5]
    threshold = rng.probability_threshold(torch.rand(n_envs, device=device))
    d = torch.randint(0, 2, (n_envs,), device=device)
    t = torch.zeros(n_envs, dtype=torch.int32, device=device)
    actions = torch.randint(0, 4, (64, n_envs), device=device)

    def one(i: int):
        nonlocal cell, t
        gust = rng.bernoulli_i32(key, t, threshold)
        cell, term = windy.step(model, cell, actions[i % 64], d, gust)
        t = t + 1
        return term

    for i in range(5):
        one(i)
    sync(device)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for i in range(20):
            one(i)
        steps += 20
        sync(device)
    return steps * n_envs / (time.perf_counter() - t0)


class _RandomAction(nn.Module):
    """A near-free random policy: cycles through 64 pre-drawn action rows (measures the env, not it)."""

    def __init__(self, n_envs: int, device: torch.device):
        super().__init__()
        gen = torch.Generator(device=device).manual_seed(0)
        self.register_buffer(
            "table", torch.randint(0, 4, (64, n_envs), device=device, generator=gen)
        )
        self.t = 0

    def forward(self, cell: torch.Tensor) -> torch.Tensor:
        self.t += 1
        return self.table[self.t % 64]


class _RandomPolicy(TensorDictModuleBase):
    """The same actions as :class:`_RandomAction`, written straight into the tensordict."""

    in_keys = ["cell"]
    out_keys = ["action"]

    def __init__(self, n_envs: int, device: torch.device):
        super().__init__()
        self.inner = _RandomAction(n_envs, device)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.inner.t += 1
        return tensordict.set("action", self.inner.table[self.inner.t % 64])


STEPS_PER_BATCH = 16


def bench_collector(n_envs: int, seconds: float, device: torch.device, improved: bool) -> float:
    env = WindyGridEnv(num_envs=n_envs, seed=0, validate_actions=False, device=device)
    if improved:
        policy = _RandomPolicy(n_envs, device)
        options = dict(track_traj_ids=False, return_same_td=True)
    else:
        policy = TensorDictModule(
            _RandomAction(n_envs, device), in_keys=["cell"], out_keys=["action"]
        )
        options = {}
    collector = Collector(
        env,
        policy,
        frames_per_batch=n_envs * STEPS_PER_BATCH,
        total_frames=-1,
        device=device,
        trust_policy=True,
        compact_obs=True,
        auto_register_policy_transforms=False,
        **options,
    )
    it = iter(collector)
    next(it)
    sync(device)
    frames, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        batch = next(it)
        frames += batch.numel()
    sync(device)
    rate = frames / (time.perf_counter() - t0)
    collector.shutdown()
    return rate


def bench_fast(n_envs: int, seconds: float, device: torch.device) -> float:
    env = WindyGridEnv(num_envs=n_envs, seed=0, validate_actions=False, device=device)
    policy = _RandomPolicy(n_envs, device)
    batch = rollout_fast(env, policy, STEPS_PER_BATCH, compact_obs=True)
    sync(device)
    frames, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        batch = rollout_fast(env, policy, STEPS_PER_BATCH, compact_obs=True, out=batch)
        frames += batch.numel()
    sync(device)
    return frames / (time.perf_counter() - t0)


def run(threads: int, args: argparse.Namespace, device: torch.device, secs: float) -> None:
    torch.set_num_threads(threads)
    print(f"-- threads={torch.get_num_threads()}")
    a = bench_gym(secs)
    print(f"(a)  gymnasium loop, taskvar/WindyGrid-v0          : {a / 1e6:10.3f} M steps/s")
    raw = {}
    for n in [int(x) for x in args.sizes.split(",")]:
        raw[n] = bench_raw(n, secs, device)
        print(f"(b)  raw batched step, N={n:<8d}                 : {raw[n] / 1e6:10.3f} M steps/s")
    print(f"ratio b(N={max(raw)})/a = {raw[max(raw)] / a:8.1f}x")
    for n in [int(x) for x in args.collector_n.split(",")]:
        c0 = bench_collector(n, secs * 2, device, improved=False)
        print(f"(c0) Collector, as first measured, N={n:<8d}     : {c0 / 1e6:10.3f} M steps/s")
        c1 = bench_collector(n, secs * 2, device, improved=True)
        print(f"(c1) Collector, improved, N={n:<8d}              : {c1 / 1e6:10.3f} M steps/s")
        c2 = bench_fast(n, secs * 2, device)
        print(f"(c2) fast path rollout_fast, N={n:<8d}           : {c2 / 1e6:10.3f} M steps/s")
        b = raw.get(n, max(raw.values()))
        print(
            f"ratios N={n}: c1/c0 = {c1 / c0:.2f}x, c2/c0 = {c2 / c0:.2f}x, c2/c1 = {c2 / c1:.2f}x, "
            f"c0/b = {c0 / b:.3f}, c2/b = {c2 / b:.3f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--threads", default=None, help="torch thread counts, one run each (default 1,2)"
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="short timings; 1 thread, N=1,1024 and 1024 for (c) unless given (smoke run)",
    )
    ap.add_argument("--sizes", default=None, help="N values for (b) (default 1,1024,16384,262144)")
    ap.add_argument("--collector-n", default=None, help="N values for (c) (default 16384)")
    args = ap.parse_args()
    args.threads = args.threads or ("1" if args.quick else "1,2")
    args.sizes = args.sizes or ("1,1024" if args.quick else "1,1024,16384,262144")
    args.collector_n = args.collector_n or ("1024" if args.quick else "16384")
    device = torch.device(args.device)
    secs = 0.3 if args.quick else 2.0
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, device={device}, load average {load:.2f}")
    for threads in [int(x) for x in args.threads.split(",")]:
        run(threads, args, device, secs)


if __name__ == "__main__":
    main()
