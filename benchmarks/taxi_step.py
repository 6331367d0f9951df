"""Taxi step throughput, measured side by side in one run, single-threaded.

(a) a Python loop over Gymnasium's own ``Taxi-v4`` (``gymnasium.make("Taxi-v4", is_rainy=True,
    fickle_passenger=True)``, with its wrappers: the time limit, order enforcing, checker);
(a2) a Python loop over our ``TaxiGymEnv`` (``taskvar/Taxi-v0``'s class, the ``storm`` instances);
(b) the batched step ``TaxiEnv._advance`` (keyed rain and fickle-redraw draws, the pure
    ``taxi.step``, the step counter) at several N, ``storm`` instances (rain and fickle on);
(c) ``TaxiEnv.step_and_maybe_reset``: the whole TorchRL step with tensordicts and partial resets,
    with the 500-dim ``onehot`` and the 19-dim ``factored`` observation (at large N the one-hot
    observation, 2 KB a sub-env, dominates: it is written and copied every step).

Usage: ``python benchmarks/taxi_step.py [--device cpu] [--sizes 1,1024,65536] [--quick]``.
Prints steps/s of each and the ratios to (a).
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import numpy as np
import torch

from taskvar_torch.families.taxi.env import TaxiEnv
from taskvar_torch.families.taxi.gym_env import TaxiGymEnv


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def bench_gym_loop(env: gym.Env, seconds: float) -> float:
    """Steps/s of a Python loop over one Gymnasium env with uniformly random actions."""
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 6, 100_000).tolist()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(1000):
            _, _, term, trunc, _ = env.step(actions[n % len(actions)])
            n += 1
            if term or trunc:
                env.reset()
    return n / (time.perf_counter() - t0)


def bench_batched(n_envs: int, seconds: float, device: torch.device) -> float:
    """Steps/s (summed over sub-envs) of ``TaxiEnv._advance``: draws + pure step + counter."""
    env = TaxiEnv(n_envs, instances="storm", seed=0, validate_actions=False, device=device)
    env.reset()
    actions = torch.randint(0, 6, (64, n_envs), device=device)
    for i in range(5):
        env._advance(actions[i])
    sync(device)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for i in range(20):
            env._advance(actions[i % 64])
        steps += 20
        sync(device)
    return steps * n_envs / (time.perf_counter() - t0)


def bench_torchrl(n_envs: int, seconds: float, device: torch.device, encoding: str) -> float:
    """Steps/s of ``TaxiEnv.step_and_maybe_reset`` (TorchRL's step with partial resets)."""
    env = TaxiEnv(
        n_envs,
        instances="storm",
        obs_encoding=encoding,
        seed=0,
        validate_actions=False,
        device=device,
    )
    td = env.reset()
    actions = torch.randint(0, 6, (64, n_envs), device=device)
    for i in range(3):
        _, td = env.step_and_maybe_reset(td.set("action", actions[i]))
    sync(device)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for i in range(10):
            _, td = env.step_and_maybe_reset(td.set("action", actions[i % 64]))
        steps += 10
        sync(device)
    return steps * n_envs / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="tiny timings and sizes (smoke run)")
    ap.add_argument("--sizes", default="1,1024,65536", help="N values for (b) and (c)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    device = torch.device(args.device)
    secs = 0.05 if args.quick else 2.0
    sizes = [1, 64] if args.quick else [int(x) for x in args.sizes.split(",")]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"torch {torch.__version__}, gymnasium {gym.__version__}, device={device}, "
        f"threads={torch.get_num_threads()}, load average {load:.2f}"
    )
    a = bench_gym_loop(gym.make("Taxi-v4", is_rainy=True, fickle_passenger=True), secs)
    print(f"(a)  gymnasium loop, Taxi-v4 rainy+fickle        : {a / 1e6:10.4f} M steps/s")
    a2 = bench_gym_loop(TaxiGymEnv(instances="storm"), secs)
    print(f"(a2) gymnasium loop, TaxiGymEnv storm            : {a2 / 1e6:10.4f} M steps/s")
    for n in sizes:
        b = bench_batched(n, secs, device)
        print(f"N={n:<7d} (b) batched step          {b / 1e6:10.4f} M steps/s ({b / a:8.1f}x a)")
        for enc in ("onehot", "factored"):
            c = bench_torchrl(n, secs, device, enc)
            print(
                f"N={n:<7d} (c) TorchRL step {enc:<8s} {c / 1e6:10.4f} M steps/s ({c / a:8.1f}x a)"
            )


if __name__ == "__main__":
    main()
