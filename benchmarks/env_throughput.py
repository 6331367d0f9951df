"""Env throughput, measured side by side in one run (docs/benchmarks.md).

(a) a Gymnasium loop over ``taskvar/WindyGrid-v0``;
(b) the raw batched windy step (keyed wind draw + dynamics + step counter) at several N;
(c) ``WindyGridEnv`` driven by TorchRL's ``Collector`` with a random policy at N=16384.

Usage: ``python benchmarks/env_throughput.py [--threads 1] [--device cpu] [--quick]``.
Prints steps/s and the ratios b/a and c/b, with the thread count.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector

import taskvar_torch  # noqa: F401
from taskvar_torch import rng
from taskvar_torch.envs import WindyGridEnv, WindyLayout, WindyModel, windy


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


def bench_collector(n_envs: int, seconds: float, device: torch.device) -> float:
    env = WindyGridEnv(num_envs=n_envs, seed=0, validate_actions=False, device=device)
    policy = TensorDictModule(_RandomAction(n_envs, device), in_keys=["cell"], out_keys=["action"])
    steps_per_batch = 16
    collector = Collector(
        env,
        policy,
        frames_per_batch=n_envs * steps_per_batch,
        total_frames=-1,
        device=device,
        trust_policy=True,
        compact_obs=True,
    )
    it = iter(collector)
    next(it)
    frames, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        batch = next(it)
        frames += batch.numel()
    sync(device)
    rate = frames / (time.perf_counter() - t0)
    collector.shutdown()
    return rate


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 = single-threaded)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="short timings (smoke run)")
    ap.add_argument("--sizes", default="1,1024,16384,262144", help="N values for (b)")
    ap.add_argument("--collector-n", type=int, default=16384, help="N for (c)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    secs = 0.3 if args.quick else 2.0
    print(f"torch {torch.__version__}, threads={torch.get_num_threads()}, device={device}")
    a = bench_gym(secs)
    print(f"(a) gymnasium loop, taskvar/WindyGrid-v0       : {a / 1e6:10.3f} M steps/s")
    raw = {}
    for n in [int(x) for x in args.sizes.split(",")]:
        raw[n] = bench_raw(n, secs, device)
        print(f"(b) raw batched step, N={n:<8d}              : {raw[n] / 1e6:10.3f} M steps/s")
    c = bench_collector(args.collector_n, secs * 2, device)
    print(f"(c) WindyGridEnv + Collector, N={args.collector_n:<8d}     : {c / 1e6:10.3f} M steps/s")
    b_max = max(raw.values())
    b_c = raw.get(args.collector_n, b_max)
    print(f"ratio b(N={max(raw)})/a = {raw[max(raw)] / a:8.1f}x")
    print(f"ratio c/b(N={args.collector_n}) = {c / b_c:8.3f}")


if __name__ == "__main__":
    main()
