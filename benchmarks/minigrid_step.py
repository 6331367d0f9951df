"""MiniGrid step throughput, measured side by side in one run, single-threaded.

(a) a Python loop over the ``minigrid`` package's own ``MiniGrid-DoorKey-5x5-v0`` (``gym.make``,
    with its wrappers), each step computing the 7 x 7 image;
(b) the port's pure batched step and view (``families/minigrid/dynamics.py`` ``step`` then
    ``view``) at several N;
(c) ``MiniGridEnv.step_and_maybe_reset``: the whole TorchRL step with the ``onehot`` observation,
    the options' state keys and partial resets.

Usage: ``python benchmarks/minigrid_step.py [--sizes 1,64,1024] [--quick]``. Prints steps/s of
each and the ratios to (a).
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid ids)
import numpy as np
import torch

from taskvar_torch.families.minigrid import dynamics as D
from taskvar_torch.families.minigrid.env import MiniGridEnv


def bench_minigrid(seconds: float) -> float:
    """Steps/s of a Python loop over MiniGrid's own DoorKey-5x5 with uniformly random actions."""
    env = gym.make("MiniGrid-DoorKey-5x5-v0")
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, D.NUM_ACTIONS, 100_000).tolist()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(200):
            _, _, term, trunc, _ = env.step(actions[n % len(actions)])
            n += 1
            if term or trunc:
                env.reset()
    return n / (time.perf_counter() - t0)


def bench_pure(n_envs: int, seconds: float) -> float:
    """Steps/s (summed over sub-envs) of the pure ``step`` and ``view`` (no resets)."""
    env = MiniGridEnv(n_envs, size=5, seed=0, validate_actions=False)
    env.reset()
    s = (env._grid, env._x, env._y, env._dir, env._carrying, env._t)
    actions = torch.randint(0, D.NUM_ACTIONS, (64, n_envs))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for i in range(10):
            grid, x, y, d, c, t, *_ = D.step(s[0], 5, *s[1:5], s[5], actions[i], 1 << 30)
            D.view(grid, 5, 5, x, y, d, c)
            s = (grid, x, y, d, c, t)
        steps += 10
    return steps * n_envs / (time.perf_counter() - t0)


def bench_torchrl(n_envs: int, seconds: float) -> float:
    """Steps/s of ``MiniGridEnv.step_and_maybe_reset`` (TorchRL's step with partial resets)."""
    env = MiniGridEnv(n_envs, size=5, seed=0, validate_actions=False)
    td = env.reset()
    actions = torch.randint(0, D.NUM_ACTIONS, (64, n_envs))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for i in range(10):
            _, td = env.step_and_maybe_reset(td.set("action", actions[i % 64]))
        steps += 10
    return steps * n_envs / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="tiny timings and sizes (smoke run)")
    ap.add_argument("--sizes", default="1,64,1024", help="N values for (b) and (c)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    secs = 0.2 if args.quick else 2.0
    sizes = [1, 64] if args.quick else [int(x) for x in args.sizes.split(",")]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, threads=1, load average {load:.2f}")
    a = bench_minigrid(secs)
    print(f"(a) minigrid loop, DoorKey-5x5        : {a / 1e3:10.2f} k steps/s")
    for n in sizes:
        b = bench_pure(n, secs)
        print(f"N={n:<6d} (b) pure step + view     {b / 1e3:10.2f} k steps/s ({b / a:7.2f}x a)")
        c = bench_torchrl(n, secs)
        print(f"N={n:<6d} (c) TorchRL step, onehot {c / 1e3:10.2f} k steps/s ({c / a:7.2f}x a)")


if __name__ == "__main__":
    main()
