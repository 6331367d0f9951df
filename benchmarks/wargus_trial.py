"""Wargus Figure 4: CPU time per paper-scale trial, TorchRL loops vs the fast loops, side by side.

Two agents from the same seed play the same trials (the loops are bit-identical, so they stay in
lockstep); trials alternate between them, so machine load hits both alike. Prints the CPU seconds
per trial of each loop, their ratio, and where the fast loop's time goes (env steps, behaviour,
replay, updates, test phases). Single-threaded.

    python benchmarks/wargus_trial.py --trials 6 [overrides like train.updates_per_batch=4]
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import torch
from torchrl.envs import InitTracker, TransformedEnv

from taskvar_torch.config import load_config
from taskvar_torch.controllers import SideBySide
from taskvar_torch.experiments import wargus_fig4 as fig4
from taskvar_torch.train import make_env


def build(cfg, torchrl: bool, seed: int = 0):
    torch.manual_seed(seed)
    env = make_env(cfg, num_envs=cfg.experiment.learning_episodes_per_trial, seed=seed)
    if torchrl:
        env = TransformedEnv(env, InitTracker())
    else:
        env.validate_actions = False
    agent = fig4.make_agent(cfg, env, seed)
    policy = SideBySide(fig4.make_test_controllers(agent), cfg.experiment.test_episodes_per_trial)
    return env, agent, policy


def timed(obj, name: str, clock: dict, label: str) -> None:
    """Wrap ``obj.name`` to add its CPU time to ``clock[label]``."""
    f = getattr(obj, name)

    def wrapper(*a, **kw):
        t = time.process_time()
        try:
            return f(*a, **kw)
        finally:
            clock[label] += time.process_time() - t

    setattr(obj, name, wrapper)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=6)
    p.add_argument("--warmup", type=int, default=2, help="untimed trials first (both loops)")
    p.add_argument("overrides", nargs="*")
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg = load_config(fig4.default_config_path(), args.overrides)
    k = cfg.experiment.test_episodes_per_trial
    ref_env, ref_agent, ref_policy = build(cfg, torchrl=True)
    ref_test_env = TransformedEnv(
        fig4.make_test_env(cfg, k, 0), ref_policy.controllers[-1].primer()
    )
    env, agent, policy = build(cfg, torchrl=False)
    clock: dict = defaultdict(float)
    for obj, name, label in (
        (env, "step_all", "env steps"),
        (agent.behaviour, "forward", "behaviour policy"),
        (agent.first_visit, "visit", "first-visit filter"),
        (agent.buffer, "extend", "replay extend"),
        (agent.buffer, "sample", "replay sample"),
        (agent.learner, "update", "gradient updates"),
    ):
        timed(obj, name, clock, label)
    ref_s = fast_s = test_s = 0.0
    snapshots = []
    frames = updates = 0
    for trial in range(args.warmup + args.trials):
        on = trial >= args.warmup
        if trial == args.warmup:
            clock.clear()
        t = time.process_time()
        fig4.learning_phase_torchrl(ref_agent, ref_env)
        fig4.test_phase_torchrl(ref_policy, ref_test_env, k)
        ref_s += (time.process_time() - t) * on
        t = time.process_time()
        u = agent.updates
        learned = fig4.learning_phase(agent, env)
        snapshots.append(policy.head_values.snapshot())
        fast_s += (time.process_time() - t) * on
        frames += learned["frames"] * on
        updates += (agent.updates - u) * on
    t = time.process_time()
    test_env = fig4.make_test_env(cfg, k, 0, 0, len(snapshots))
    fig4.test_trials(policy, test_env, k, snapshots)
    test_s = (time.process_time() - t) * args.trials / len(snapshots)
    fast_s += test_s
    n = args.trials
    print(
        f"CPU seconds per trial over {n} trials (after {args.warmup} warm-up), 1 thread, "
        f"{frames / n:.0f} frames and {updates / n:.0f} updates per trial:"
    )
    print(f"  TorchRL loops (EnvBase + transforms, per-trial test) {ref_s / n:7.2f}")
    print(
        f"  fast loops (pure dynamics, tests {len(snapshots)} trials side by side) {fast_s / n:7.2f}"
        f"   ratio {ref_s / max(fast_s, 1e-9):.2f}x"
    )
    print("  fast loop split per trial:")
    learn_s = fast_s - test_s
    for label, s in sorted(clock.items(), key=lambda kv: -kv[1]):
        print(f"    {label:<22}{s / n:7.3f}")
    print(f"    {'other learning loop':<22}{(learn_s - sum(clock.values())) / n:7.3f}")
    print(f"    {'test phases':<22}{test_s / n:7.3f}")
    if updates:
        print(f"  per gradient update: {clock['gradient updates'] / updates * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
