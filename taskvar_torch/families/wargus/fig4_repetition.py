"""Repetitions of the Wargus Figure 4 protocol (paper §3.5.1-3.5.3; docs/wargus-fig4.md), batched
(:func:`run_repetitions_batched`) or alone (:func:`run_repetition`), each giving the numbers it
gives alone; :func:`heldout_summary`.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from taskvar_torch import keys
from taskvar_torch.checkpoint import make_bundle, rng_state, save_checkpoint
from taskvar_torch.config import Config
from taskvar_torch.contract import HELDOUT_SEEDS
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.experiments.curves import (
    trials_to_fraction_of_max,
)
from taskvar_torch.factory import (
    make_env,
)
from taskvar_torch.families.wargus.dynamics import WargusInstances
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.fig4_agent import (
    make_agent,
    make_behaviour,
    make_heldout_test_env,
    make_test_controllers,
    make_test_env,
    trial_calibration,
)
from taskvar_torch.families.wargus.fig4_metrics import (
    METHODS,
    mean_over_trials,
    method_summary,
    summarise,
)
from taskvar_torch.families.wargus.fig4_recurrent import PHASES as RECURRENT_PHASES
from taskvar_torch.families.wargus.fig4_trial import (
    LifelongAgent,
    learning_phases,
    repetition_seed,
    test_trials,
)
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.heads.seeds import load_seed, stack_seeds

TEST_GROUP = 25  # trials whose test phases run side by side (run_repetition)
HELDOUT_CSV = "per_trial_heldout.csv"
"""The held-out test phases' rows (``per_trial.csv``'s columns)."""
BASELINES_CSV = "per_trial_baselines.csv"
"""The baselines' test phases (``experiment.baselines``): rep, trial, method, nominal items and
held-out items per test episode."""
BASELINES_CSV_FIELDS = ("rep", "trial", "method", "items", "heldout_items")
HELDOUT_KEYS = ("items", "interruptions", "control_steps", "item_lost")
"""What a held-out test phase records per trial (``run_repetition``'s ``heldout_*``)."""
PHASES = ("learning_loop", "updates", "calibration", "test")
"""Where a repetition's CPU time goes (``metrics.json`` ``timing.cpu_seconds_per_trial``): the
learning phases' loop (behaviour, dynamics, replay writes), the gradient updates (replay samples
included), the hierarchy's calibration and the heads' snapshot after each trial, the test phases
(compiles, with ``train.compile``, fall in the phase that first runs the compiled code)."""


# --------------------------------------------------------------------------------------------
# one repetition


@dataclasses.dataclass
class _Repetition:
    """One repetition's protocol state around its agent: its test policy, the rows recorded so
    far, the frozen heads and calibrations of trials not tested yet, CPU seconds per phase."""

    rep: int
    seed: int
    agent: LifelongAgent
    learn_env: WargusEnv
    policy: SideBySide
    group: int
    rows: dict[str, list]
    updates: list[int] = dataclasses.field(default_factory=list)
    snapshots: list[list[torch.Tensor]] = dataclasses.field(default_factory=list)
    calibrations: list[RobustnessCalibration | None] = dataclasses.field(default_factory=list)
    cpu: dict[str, float] = dataclasses.field(default_factory=lambda: dict.fromkeys(PHASES, 0.0))


def _start_repetition(cfg: Config, rep: int, test_group: int) -> _Repetition:
    """A fresh agent (paper §3.5.1), its learning env and test policy; draws the networks'
    initialisation from the global stream seeded :func:`repetition_seed` (the caller's
    ``fork_rng`` scope)."""
    x = cfg.experiment
    seed = repetition_seed(cfg, rep)
    rep_cfg = dataclasses.replace(cfg, seed=seed)
    torch.manual_seed(seed)
    learn_env = make_env(rep_cfg, num_envs=x.learning_episodes_per_trial, seed=seed)
    learn_env.validate_actions = False  # the behaviour's actions are in range by construction
    if cfg.train.compile:  # the learning loop's dynamics too (the learner: make_agent)
        learn_env.compile_dynamics()
    agent = make_agent(rep_cfg, learn_env, seed)
    policy = SideBySide(make_test_controllers(agent), x.test_episodes_per_trial)
    keys_ = ("items", "interruptions", "control_steps", "item_lost", "learn_items", "frames")
    rows = {k: [] for k in (*keys_, *(f"heldout_{k}" for k in HELDOUT_KEYS))}
    group = test_group if policy.batchable else 1
    return _Repetition(rep, seed, agent, learn_env, policy, group, rows)


def _test_env(
    make: Callable[..., WargusEnv], cfg: Config, runs: Sequence[_Repetition], first: int, G: int
) -> WargusEnv:
    """``make`` (:func:`make_test_env` or :func:`make_heldout_test_env`) of ``G`` trials from
    ``first`` for every repetition of ``runs`` at once: their rows in seed-major blocks, block
    ``s`` drawing what repetition ``s``'s own test env draws (:meth:`WargusEnv.set_seed_blocks`)."""
    k = cfg.experiment.test_episodes_per_trial
    if len(runs) == 1:
        return make(cfg, k, runs[0].seed, first_trial=first, trials=G)
    one = make(cfg, k, runs[0].seed, first_trial=first, trials=G)
    rows = one.instances.seeds * len(runs)
    env = make_env(
        cfg,
        len(rows),
        seed=runs[0].seed,
        instances=WargusInstances(seeds=rows),
        validate_actions=False,
    )
    env.set_seed_blocks([r.seed for r in runs])
    return env


def _test_pending(cfg: Config, runs: Sequence[_Repetition]) -> None:
    """Test phases of the trials not tested yet, every repetition side by side on its own rows."""
    tick = time.process_time()
    k = cfg.experiment.test_episodes_per_trial
    if runs[0].group == 1 and len(runs) > 1:
        for r in runs:
            _test_pending(cfg, [r])
        return
    G = len(runs[0].snapshots)
    policy = runs[0].policy
    snaps = [snap for r in runs for snap in r.snapshots] if runs[0].group > 1 else None
    cals = [c for r in runs for c in r.calibrations]
    if runs[0].group == 1 and cals[0] is not None:
        policy.controllers[METHODS.index("hierarchy")].calibration = cals[0]
    first = len(runs[0].rows["items"])
    env = _test_env(make_test_env, cfg, runs, first, G)
    tested = test_trials(policy, env, k, snaps, cals)
    for i, r in enumerate(runs):
        for one in tested[i * G : (i + 1) * G]:
            for key, v in one.items():
                r.rows[key].append(v)
    first = len(runs[0].rows["heldout_items"])
    env = _test_env(make_heldout_test_env, cfg, runs, first, G)
    tested = test_trials(policy, env, k, snaps, cals)
    for i, r in enumerate(runs):
        for one in tested[i * G : (i + 1) * G]:
            for key in HELDOUT_KEYS:
                r.rows[f"heldout_{key}"].append(one[key])
        r.snapshots.clear()
        r.calibrations.clear()
    spent = (time.process_time() - tick) / len(runs)
    for r in runs:
        r.cpu["test"] += spent


def _end_trial(cfg: Config, r: _Repetition, learned: dict[str, float]) -> None:
    """Record a learning phase, freeze the heads and calibrate."""
    for key, v in learned.items():
        r.rows[key].append(v)
    r.updates.append(r.agent.updates)
    tick = time.process_time()
    r.snapshots.append(r.policy.head_values.snapshot() if r.group > 1 else [])
    r.calibrations.append(trial_calibration(r.agent))
    r.cpu["calibration"] += time.process_time() - tick


def _finish(cfg: Config, r: _Repetition, out_dir: str | os.PathLike) -> dict[str, Any]:
    """Save ``rep{rep}/final.pt``, return the repetition's result (every trial tested)."""
    r.rows["updates"] = r.updates
    agent = r.agent
    save_checkpoint(
        Path(out_dir) / f"rep{r.rep}" / "final.pt",
        make_bundle(
            agent.cfg,
            models={"heads": agent.heads, "targets": agent.learner.loss.target_heads},
            optimizers={"adam": agent.learner.optimizer},
            counters={
                "frames": agent.frames,
                "updates": agent.updates,
                "trials": cfg.experiment.trials,
            },
            rng=rng_state({"replay": agent.replay_generator, "explore": agent.explore_generator}),
            heads_spec=agent.heads.spec.to_dict(),
        ),
    )
    result = {key: np.asarray(v) for key, v in r.rows.items()}
    result["option_names"] = list(agent.heads.option_names)
    result["option_depths"] = hierarchy_depths(agent.subtasks.hierarchy, agent.heads.option_names)
    result["cpu_seconds"] = r.cpu
    return result


def run_repetitions_batched(
    cfg: Config,
    reps: Sequence[int],
    out_dir: str | os.PathLike,
    on_trial: Callable[[int, int], None] | None = None,
    test_group: int = TEST_GROUP,
) -> list[dict[str, Any]]:
    """Repetitions ``reps`` in one batched loop; saves each ``rep{rep}/final.pt``.

    Each repetition keeps its own agent, generators, schedule and test phases
    (:func:`learning_phases`, docs/seeds.md#figure-4-repetitions), so its numbers are those it gives
    alone; ``test_group`` trials are tested side by side on frozen heads (:func:`test_trials`). Runs
    inside :func:`torch.random.fork_rng`.

    Returns, per repetition:
        ``items``, ``interruptions``, ``item_lost`` ``(T, M)``, ``control_steps`` ``(T, O)``,
        ``learn_items``, ``frames``, ``updates`` ``(T,)``, ``option_names``, ``seconds`` and
        ``cpu_seconds`` per :data:`PHASES`.
    """
    start = time.perf_counter()
    S = len(reps)
    with torch.random.fork_rng(devices=[]):
        runs = [_start_repetition(cfg, rep, test_group) for rep in reps]
        agents = [r.agent for r in runs]
        if S == 1:
            env, behaviour, first_visit, on_update = (
                runs[0].learn_env,
                agents[0].behaviour,
                agents[0].first_visit,
                None,
            )
        else:
            env = make_env(cfg, num_envs=S * cfg.experiment.learning_episodes_per_trial)
            env.set_seed_blocks([r.seed for r in runs])
            env.validate_actions = False
            if cfg.train.compile:
                env.compile_dynamics()
            acting = stack_seeds([a.heads for a in agents])
            generators = [a.explore_generator for a in agents]
            behaviour = make_behaviour(cfg, acting, agents[0].subtasks, env.action_spec, generators)
            obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
            first_visit = FirstVisitFilter(env.num_envs, obs_dim, device=cfg.device)

            def on_update(s: int) -> None:  # repetition s learnt: the acting stack follows
                load_seed(acting, s, agents[s].heads)

        for trial in range(cfg.experiment.trials):
            tick, before = time.process_time(), [a.update_seconds for a in agents]
            learned = learning_phases(agents, env, behaviour, first_visit, on_update)
            spent = [a.update_seconds - b for a, b in zip(agents, before)]
            loop = (time.process_time() - tick - sum(spent)) / S
            for r, u, one in zip(runs, spent, learned):
                r.cpu["updates"] += u
                r.cpu["learning_loop"] += loop
                _end_trial(cfg, r, one)
            if len(runs[0].snapshots) >= runs[0].group:
                _test_pending(cfg, runs)
            for r in runs:
                if on_trial is not None:
                    on_trial(r.rep, trial)
        if runs[0].snapshots:
            _test_pending(cfg, runs)
        results = [_finish(cfg, r, out_dir) for r in runs]
    for result in results:
        result["seconds"] = time.perf_counter() - start
    return results


def run_repetition(
    cfg: Config,
    rep: int,
    out_dir: str | os.PathLike,
    on_trial: Callable[[int, int], None] | None = None,
    test_group: int = TEST_GROUP,
) -> dict[str, Any]:
    """Repetition ``rep`` of the lifelong protocol alone: :func:`run_repetitions_batched` of one
    (module docstring; saves ``rep{rep}/final.pt``)."""
    return run_repetitions_batched(cfg, [rep], out_dir, on_trial, test_group)[0]


def _add_baseline(
    metrics: dict[str, Any], name: str, results: Sequence[dict[str, Any]], seconds: float
) -> None:
    """A baseline's curves (``experiment.baselines``) into ``metrics``: its entry beside the
    paper's methods, nominal (``methods``) and held-out (``heldout.methods``), and its cost
    (``timing.baselines``)."""
    items = np.stack([r["items"] for r in results])  # (R, T)
    held = np.stack([r["heldout_items"] for r in results])
    metrics["methods"][name] = method_summary(items)
    metrics["heldout"]["methods"][name] = {**method_summary(held), **heldout_extras(held)}
    n = max(items.size, 1)
    metrics["timing"].setdefault("baselines", {})[name] = {
        "wall_seconds": seconds,
        "frames_per_repetition": [int(r["frames"].sum()) for r in results],
        "updates_per_repetition": [int(r["updates"][-1]) for r in results],
        "cpu_seconds_per_trial": {
            phase: sum(r["cpu_seconds"][phase] for r in results) / n for phase in RECURRENT_PHASES
        },
    }


def heldout_extras(items: np.ndarray) -> dict[str, Any]:
    """What a held-out method entry adds to :func:`method_summary` for the claims (``taskvar
    report``), from ``items`` ``(R, T)``: the mean over the first half of the trials and each
    repetition's trials to 90% of its own maximum."""
    items = np.asarray(items, dtype=float)
    return {
        "mean_first_half": mean_over_trials(items, max(items.shape[1] // 2, 1)),
        "trials_to_90pct_of_max_per_rep": [trials_to_fraction_of_max(c) for c in items],
    }


def heldout_summary(held: dict[str, np.ndarray], first: dict[str, Any]) -> dict[str, Any]:
    """``metrics.json``'s ``heldout``: :func:`summarise` of the held-out test phases (the same
    keys as the nominal figures at the top level), and which instances they played."""
    m = summarise(
        held["items"],
        held["interruptions"],
        held["control_steps"],
        first["option_names"],
        first["option_depths"],
        held["item_lost"],
    )
    m.pop("experiment")
    m["definitions"]["score"] = "items collected per held-out test episode"
    for i, name in enumerate(METHODS):  # the claims' figures (taskvar report), per repetition
        m["methods"][name].update(heldout_extras(held["items"][:, :, i]))
    m["definitions"]["mean_first_half"] = "mean_over_trials over trials 1..T/2"
    m["definitions"]["trials_to_90pct_of_max_per_rep"] = (
        "trials_to_90pct_of_max of each repetition's own curve"
    )
    m["instances"] = {
        "first_seed": HELDOUT_SEEDS[0],
        "count": len(HELDOUT_SEEDS),
        "order": "trial t, episode j plays seed (t K + j) mod count (every method the same)",
    }
    return m


def hierarchy_depths(hierarchy: Any, option_names: Sequence[str]) -> list[int]:
    """Depth of each option in the composition tree (0: the root; -1: outside the tree)."""
    depth, stack = {hierarchy.root: 0}, [hierarchy.root]
    while stack:
        o = stack.pop()
        for c in hierarchy.children.get(o, ()):
            depth[c] = depth[o] + 1
            stack.append(c)
    return [depth.get(o, -1) for o in option_names]


__all__ = [
    "BASELINES_CSV",
    "BASELINES_CSV_FIELDS",
    "HELDOUT_CSV",
    "HELDOUT_KEYS",
    "PHASES",
    "TEST_GROUP",
    "heldout_extras",
    "heldout_summary",
    "hierarchy_depths",
    "run_repetition",
    "run_repetitions_batched",
]
