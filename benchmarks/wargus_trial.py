"""Wargus Figure 4: CPU time per paper-scale trial, the old fast path vs the new, side by side.

Two agents from the same seed play the same protocol, trials alternating between them so machine
load hits both alike:

* **old path**: the behaviour policy runs each head on its own (``BehaviourPolicy(stacked=False)``)
  and the learner and dynamics run eager (``train.compile=false``): the fast loops as they were
  before issue 13, but for the first-visit filter (now once per update phase in both);
* **new path**: the behaviour reads its heads from one stacked pass, and the behaviour's choices,
  the learner's losses and the dynamics step run through ``torch.compile``
  (``train.compile=true``; ``--eager``: eager).

A trial is what :func:`~taskvar_torch.families.wargus.fig4_repetition.run_repetition` does per trial: the
learning phase, the hierarchy's calibration, a snapshot of the heads, and the test phase (the
trials' test phases run side by side at the end, ``TEST_GROUP`` at a time as in the protocol, and
their cost is shared out per trial). The compiled learner may differ from the eager one in the
last float bits, so the two agents can drift apart over the trials (their frames and updates per
trial are printed). Prints the CPU seconds per trial of each path, their ratio, the compile time
(wall, once per process: Inductor compiles in worker processes whose CPU ``process_time`` does not
see), where the new path's time goes, and the projected wall time of the full protocol
(``configs/wargus.yaml``: runs x trials, one repetition per process on 2 cores). Single-threaded.
``--torchrl`` adds the TorchRL reference loops (EnvBase + transforms, per-trial tests);
``--bf16`` a third agent, the new path with the learner's matmuls in bfloat16
(``train.matmul_dtype=bfloat16``); ``--hidden 64,64`` one more, the new path with narrower
networks (``heads.hidden``; docs/benchmarks.md).

    python benchmarks/wargus_trial.py --trials 6 [--eager] [--torchrl] [--bf16] [--hidden W,W]
        [--quick] [overrides ...]

``--quick``: a smoke run (1 trial, no warm-up, eager, a 16x16 grid, short episodes, few envs).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch
from torchrl.envs import InitTracker, TransformedEnv

from taskvar_torch.config import load_config
from taskvar_torch.controllers import SideBySide
from taskvar_torch.factory import make_env
from taskvar_torch.families.wargus import fig4, fig4_agent, fig4_repetition, fig4_trial
from taskvar_torch.heads.behaviour import BehaviourPolicy

sys.path.insert(0, str(Path(__file__).resolve().parent / "reference"))
import wargus_torchrl_trial as reference  # noqa: E402  (the TorchRL reference loops, --torchrl)

CORES = 2  # this project's machine
QUICK = [  # --quick: a smoke run, first (the command line's overrides come after)
    "env.wargus.size=16",
    "env.wargus.horizon=40",
    "experiment.learning_episodes_per_trial=4",
    "experiment.test_episodes_per_trial=2",
    "train.init_random_frames=8",
    "train.batch_size=32",
    "train.frames_per_batch=8",
    "heads.hidden=[32,32]",
]


def build(cfg, torchrl: bool = False, stacked: bool = True, seed: int = 0):
    torch.manual_seed(seed)
    env = make_env(cfg, num_envs=cfg.experiment.learning_episodes_per_trial, seed=seed)
    if torchrl:
        env = TransformedEnv(env, InitTracker())
    else:
        env.validate_actions = False
    agent = fig4_agent.make_agent(cfg, env, seed)
    if not stacked:  # the old behaviour: each head on its own
        agent.behaviour = BehaviourPolicy(
            agent.heads,
            agent.subtasks,
            env.action_spec,
            option_prob=cfg.train.option_behaviour_prob,
            root_policy=cfg.train.hierarchy_root_policy,
            stacked=False,
        )
    policy = SideBySide(
        fig4_agent.make_test_controllers(agent), cfg.experiment.test_episodes_per_trial
    )
    return env, agent, policy


def sync(device: torch.device | str) -> None:
    """Wait for ``device``'s queued kernels before a clock is read (CUDA runs asynchronously)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def timed(obj, name: str, clock: dict, label: str, device: torch.device | str = "cpu") -> None:
    """Wrap ``obj.name`` to add its CPU time to ``clock[label]``."""
    f = getattr(obj, name)

    def wrapper(*a, **kw):
        sync(device)
        t = time.process_time()
        try:
            return f(*a, **kw)
        finally:
            sync(device)
            clock[label] += time.process_time() - t

    setattr(obj, name, wrapper)


class Path:
    """One agent playing the fast loops, with its CPU clock and its untested trials."""

    def __init__(self, cfg, stacked: bool, clock: dict | None = None):
        self.cfg = cfg
        self.env, self.agent, self.policy = build(cfg, stacked=stacked)
        if cfg.train.compile:  # as run_repetition
            self.env.compile_dynamics()
        self.seconds = self.frames = self.updates = 0.0
        self.snapshots, self.calibrations = [], []
        self.compile_wall = 0.0  # wall seconds of the first step, action and update (compiles)
        self.clock = clock
        if clock is not None:
            a = self.agent
            for obj, name, label in (
                (self.env, "step_all", "env steps"),
                (a.behaviour, "forward", "behaviour policy"),
                (a.first_visit, "visit_steps", "first-visit filter"),
                (a.buffer, "extend", "replay extend"),
                (a.buffer, "sample", "replay sample"),
                (a.learner, "update", "gradient updates"),
            ):
                timed(obj, name, clock, label, cfg.device)
        a = self.agent
        for obj, name in ((self.env, "step_all"), (a.behaviour, "forward"), (a.learner, "update")):
            self._time_first_call(obj, name)

    def _time_first_call(self, obj, name: str) -> None:
        """Add the wall time of ``obj.name``'s first call (its compile, if any) to
        ``compile_wall``."""
        f = getattr(obj, name)

        def first(*a, **kw):
            sync(self.cfg.device)
            w = time.perf_counter()
            out = f(*a, **kw)
            sync(self.cfg.device)
            self.compile_wall += time.perf_counter() - w
            setattr(obj, name, f)
            return out

        setattr(obj, name, first)

    def trial(self, on: bool) -> None:
        a, u, device = self.agent, self.agent.updates, self.cfg.device
        sync(device)
        t = time.process_time()
        learned = fig4_trial.learning_phase(a, self.env)
        sync(device)
        c = time.process_time()
        self.calibrations.append(fig4_agent.trial_calibration(a))
        sync(device)
        if self.clock is not None:
            self.clock["calibration"] += time.process_time() - c
        self.snapshots.append(self.policy.head_values.snapshot())
        sync(device)
        self.seconds += (time.process_time() - t) * on
        self.frames += learned["frames"] * on
        self.updates += (a.updates - u) * on

    def test(self, trials: int) -> float:
        """Test every trial played, TEST_GROUP side by side; CPU seconds per timed trial."""
        k = self.cfg.experiment.test_episodes_per_trial
        sync(self.cfg.device)
        t = time.process_time()
        n = len(self.snapshots)
        for g in range(0, n, fig4_repetition.TEST_GROUP):
            snaps, cals = (
                self.snapshots[g : g + fig4_repetition.TEST_GROUP],
                self.calibrations[g : g + fig4_repetition.TEST_GROUP],
            )
            env = fig4_agent.make_test_env(self.cfg, k, 0, g, len(snaps))
            fig4_trial.test_trials(self.policy, env, k, snaps, cals)
        sync(self.cfg.device)
        s = (time.process_time() - t) / n
        self.seconds += s * trials
        return s


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=6)
    p.add_argument(
        "--warmup", type=int, default=2, help="untimed trials first (both paths; >= 2: the compile)"
    )
    p.add_argument("--eager", action="store_true", help="new path with train.compile=false")
    p.add_argument("--torchrl", action="store_true", help="also time the TorchRL loops")
    p.add_argument(
        "--bf16",
        action="store_true",
        help="also time the new path with train.matmul_dtype=bfloat16 (the learner's matmuls)",
    )
    p.add_argument(
        "--hidden",
        default=None,
        help="also time the new path with these hidden widths (heads.hidden), e.g. 64,64",
    )
    p.add_argument("--quick", action="store_true", help="1 eager trial, tiny sizes (smoke run)")
    p.add_argument("overrides", nargs="*")
    args = p.parse_args()
    if args.quick:
        args.trials, args.warmup, args.eager = 1, 0, True
    torch.set_num_threads(1)
    cfg = load_config(fig4.default_config_path(), [*(QUICK if args.quick else []), *args.overrides])
    old_cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, compile=False))
    new_cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, compile=not args.eager))
    clock: dict = defaultdict(float)
    old, new = Path(old_cfg, stacked=False), Path(new_cfg, stacked=True, clock=clock)
    paths = [new, old]
    if args.bf16:
        bf16_cfg = dataclasses.replace(
            new_cfg, train=dataclasses.replace(new_cfg.train, matmul_dtype="bfloat16")
        )
        bf16 = Path(bf16_cfg, stacked=True)
        paths.append(bf16)
    if args.hidden:
        widths = [int(w) for w in args.hidden.split(",")]
        narrow_cfg = dataclasses.replace(
            new_cfg, heads=dataclasses.replace(new_cfg.heads, hidden=tuple(widths))
        )
        narrow = Path(narrow_cfg, stacked=True)
        paths.append(narrow)
    if args.torchrl:
        k = cfg.experiment.test_episodes_per_trial
        ref_env, ref_agent, ref_policy = build(old_cfg, torchrl=True)
        ref_test_env = TransformedEnv(
            fig4_agent.make_test_env(cfg, k, 0), ref_policy.controllers[-1].primer()
        )
    ref_s = 0.0
    for trial in range(args.warmup + args.trials):
        on = trial >= args.warmup
        if trial == args.warmup:
            clock.clear()
        for path in paths[::-1] if trial % 2 else paths:  # alternate: load hits all alike
            path.trial(on)
        if args.torchrl:
            sync(cfg.device)
            t = time.process_time()
            reference.learning_phase_torchrl(ref_agent, ref_env)
            reference.test_phase_torchrl(ref_policy, ref_test_env, k)
            sync(cfg.device)
            ref_s += (time.process_time() - t) * on
    old.test(args.trials)
    test_new = new.test(args.trials)
    if args.bf16:
        bf16.test(args.trials)
    if args.hidden:
        narrow.test(args.trials)
    n = args.trials
    x = cfg.experiment
    compiled = new.agent.learner.losses is not new.agent.learner.loss.losses
    print(
        f"CPU seconds per paper-scale trial over {n} trials (after {args.warmup} warm-up), 1 thread"
    )
    if args.torchrl:
        print(f"  TorchRL loops (EnvBase + transforms, per-trial test)        {ref_s / n:6.3f}")
    print(
        f"  old path (each head on its own in the behaviour, all eager)     {old.seconds / n:6.3f}"
        f"   {old.frames / n:.0f} frames, {old.updates / n:.0f} updates per trial"
    )
    print(
        f"  new path (one stacked behaviour pass, "
        f"{'all compiled' if compiled else 'eager'})             {new.seconds / n:6.3f}"
        f"   {new.frames / n:.0f} frames, {new.updates / n:.0f} updates per trial"
    )
    print(
        f"  ratio old / new {old.seconds / max(new.seconds, 1e-9):.2f}x per trial, "
        f"{old.seconds / max(old.frames, 1) / max(new.seconds / max(new.frames, 1), 1e-12):.2f}x "
        "per frame (the agents drift apart: compiled losses differ in the last bits)"
    )
    if args.bf16:
        print(
            f"  new path, learner matmuls in bfloat16 (train.matmul_dtype)   {bf16.seconds / n:6.3f}"
            f"   {bf16.frames / n:.0f} frames, {bf16.updates / n:.0f} updates per trial; "
            f"ratio new / bfloat16 {new.seconds / max(bf16.seconds, 1e-9):.2f}x per trial"
        )
    if args.hidden:
        print(
            f"  new path, heads.hidden=[{args.hidden}]                    {narrow.seconds / n:6.3f}"
            f"   {narrow.frames / n:.0f} frames, {narrow.updates / n:.0f} updates per trial; "
            f"ratio new / narrow {new.seconds / max(narrow.seconds, 1e-9):.2f}x per trial"
        )
    if compiled:
        print(
            f"  compile (the new path's first env step, action and update): "
            f"{new.compile_wall:.1f} s wall"
        )
    print("  new path split per trial:")
    learn_s = new.seconds - test_new * n
    for label, s in sorted(clock.items(), key=lambda kv: -kv[1]):
        print(f"    {label:<26}{s / n:7.3f}")
    other = (learn_s - sum(clock.values())) / n
    print(f"    {'other learning loop':<26}{other:7.3f}")
    print(f"    {'test phases':<26}{test_new:7.3f}")
    if new.updates:
        print(f"  per gradient update: {clock['gradient updates'] / new.updates * 1e3:.1f} ms")
    trials = x.runs * x.trials
    projected = [("old", old, 0.0), ("new", new, new.compile_wall if compiled else 0)]
    if args.bf16:
        projected.append(("bfloat16", bf16, bf16.compile_wall if compiled else 0))
    if args.hidden:
        projected.append((f"hidden {args.hidden}", narrow, narrow.compile_wall if compiled else 0))
    for name, path, extra in projected:
        wall = (trials * path.seconds / n + x.runs * extra) / CORES
        print(
            f"  projected {x.runs} x {x.trials} protocol on {CORES} cores, {name} path: "
            f"{wall / 60:.1f} min ({trials} trials / {CORES} cores x s/trial"
            + (f" + {x.runs} compiles" if extra else "")
            + ")"
        )


if __name__ == "__main__":
    main()
