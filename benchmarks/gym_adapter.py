"""MiniGrid DoorKey-5x5 step throughput, raw and through the Gymnasium adapter, side by side in one
run, single-threaded (issue 46; docs/gymnasium.md).

(a) raw MiniGrid: a Python loop over ``N`` ``gym.make("MiniGrid-DoorKey-5x5-v0")`` envs, uniformly
    random actions, a reset where an episode ends (MiniGrid's own 250-step limit);
(b) the adapter (``examples/minigrid_doorkey``'s family, ``vector=sync``): ``step_and_maybe_reset``
    of its TorchRL env, which also evaluates the three options on every step, encodes the
    observation and draws each episode's instance and seed from the library's key;
(c) the same with ``vector=async`` (one process per sub-environment; started before the clock);
(d) a torch port of MiniGrid, where one is registered as family ``minigrid`` (issue 46 item 3):
    its ``step_and_maybe_reset`` under its default config at the same ``N``; skipped otherwise.

Usage: ``python benchmarks/gym_adapter.py [--n 16] [--seconds 2] [--rounds 3] [--vector sync,async]
[--quick]``. The measurements alternate for ``--rounds`` rounds (a shared machine's load falls on
all of them alike); prints each one's best steps/s (summed over sub-environments) and its ratio
to (a).
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples" / "minigrid_doorkey"))
import taskvar_doorkey  # noqa: E402

from taskvar_torch import keys  # noqa: E402
from taskvar_torch.config import apply_overrides  # noqa: E402
from taskvar_torch.config.loader import config_schema  # noqa: E402
from taskvar_torch.contract import FAMILIES, register_family  # noqa: E402

ENV_ID = "MiniGrid-DoorKey-5x5-v0"
ACTIONS = 7


def bench_raw(n: int, seconds: float) -> float:
    """Steps/s of a Python loop over ``n`` MiniGrid envs."""
    envs = [gym.make(ENV_ID) for _ in range(n)]
    for i, env in enumerate(envs):
        env.reset(seed=i)
    actions = np.random.default_rng(0).integers(0, ACTIONS, 100_003).tolist()
    steps, k, t0 = 0, 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(50):
            for env in envs:
                _, _, term, trunc, _ = env.step(actions[k % len(actions)])
                k += 1
                if term or trunc:
                    env.reset()
        steps += 50 * n
    return steps / (time.perf_counter() - t0)


def bench_family(name: str, overrides: list[str], n: int, seconds: float) -> float:
    """Steps/s of ``step_and_maybe_reset`` of family ``name``'s env at ``n`` sub-environments."""
    fam = FAMILIES[name]
    cfg = apply_overrides(config_schema(name)(family=name), overrides)
    env = fam.make_env(cfg, n, seed=0, validate_actions=False)
    actions = torch.randint(0, int(env.action_spec.space.n), (64, n))
    td = env.reset()
    for i in range(3):
        _, td = env.step_and_maybe_reset(td.set(keys.ACTION, actions[i]))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for i in range(20):
            _, td = env.step_and_maybe_reset(td.set(keys.ACTION, actions[i % 64]))
        steps += 20 * n
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=16, help="sub-environments")
    p.add_argument("--seconds", type=float, default=2.0, help="timed seconds per measurement")
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds; the best is kept")
    p.add_argument("--vector", default="sync,async", help="adapter vector envs to time")
    p.add_argument("--quick", action="store_true", help="tiny sizes (the test suite's smoke run)")
    a = p.parse_args()
    torch.set_num_threads(1)
    n, seconds, rounds = (2, 0.3, 1) if a.quick else (a.n, a.seconds, a.rounds)
    vectors = ["sync"] if a.quick else a.vector.split(",")
    register_family(taskvar_doorkey.family(), replace=True)
    print(f"MiniGrid {ENV_ID}, N={n}, {seconds:g} s each, single thread (OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS')}, torch threads {torch.get_num_threads()})")  # fmt: skip
    runs = {"(a) raw MiniGrid, N envs in a loop": lambda: bench_raw(n, seconds)}
    for vector in vectors:
        overrides = [f"env.doorkey.vector={vector}"]
        runs[f"(b) adapter, vector={vector}"] = lambda o=overrides: bench_family(
            "doorkey", o, n, seconds
        )
    if "minigrid" in FAMILIES:
        runs["(d) torch port (family minigrid)"] = lambda: bench_family("minigrid", [], n, seconds)
    else:
        print("(d) torch port: no family 'minigrid' registered; skipped")
    best = dict.fromkeys(runs, 0.0)
    for _ in range(rounds):
        for label, run in runs.items():
            best[label] = max(best[label], run())
    raw = best["(a) raw MiniGrid, N envs in a loop"]
    for label, rate in best.items():
        print(f"  {label:40s} {rate:10.0f} steps/s   x{rate / raw:.2f}")


if __name__ == "__main__":
    main()
