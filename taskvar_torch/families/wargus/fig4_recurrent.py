"""The recurrent baseline's curve in the Wargus Figure 4 protocol (docs/wargus-fig4.md#memory).

With ``experiment.baselines: [recurrent]`` each repetition also trains a fresh recurrent
Q-network through the same trials (learning on the training instances, greedy test on the
trial's nominal and held-out seeds), from its own streams, saved as ``rep{r}/recurrent.pt``.
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
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import step_mdp

from taskvar_torch import keys
from taskvar_torch.config import Config
from taskvar_torch.experiments.paired import play
from taskvar_torch.experiments.shift import EvalPoint
from taskvar_torch.factory import make_env
from taskvar_torch.families.wargus.dynamics import WargusInstances
from taskvar_torch.families.wargus.fig4_trial import repetition_seed, trial_seeds
from taskvar_torch.heads.recurrent import (
    BaselineController,
    BaselineSpec,
    baseline_path,
    make_recurrent_qnet,
    recurrent_transforms,
    save_baseline,
)
from taskvar_torch.training.baselines import BaselineLearner, stored_keys
from taskvar_torch.training.learning import epsilon_at, lr_at, non_finite, update_phase

RECURRENT_OFFSET = 1 << 33
"""The recurrent agent of the repetition seeded ``seed`` draws from torch's generator seeded
``seed + RECURRENT_OFFSET`` (network initialisation, exploration, replay samples)."""
PHASES = ("learning_loop", "updates", "test")
"""Where the recurrent agent's CPU time goes per trial (``metrics.json``
``timing.baselines.recurrent.cpu_seconds_per_trial``)."""


@dataclasses.dataclass
class RecurrentAgent:
    """One repetition's recurrent agent: network, learner (replay, loss, optimiser), learning env
    and counters."""

    cfg: Config
    seed: int
    spec: BaselineSpec
    controller: BaselineController
    learner: BaselineLearner
    env: TransformedEnv
    frames: int = 0
    pending: int = 0  # frames played since the last frames_per_batch boundary
    updates: int = 0


def make_recurrent_agent(cfg: Config, seed: int) -> RecurrentAgent:
    """A fresh recurrent agent (paper §3.5.1: no prior knowledge) and its learning env of
    ``experiment.learning_episodes_per_trial`` sub-environments (training instances, env seed
    ``seed``); the network is initialised from torch's global generator (the caller seeds it)."""
    base = make_env(cfg, num_envs=cfg.experiment.learning_episodes_per_trial, seed=seed)
    base.validate_actions = False  # random actions are drawn in range
    obs_dim = int(base.observation_spec[keys.OBSERVATION].shape[-1])
    num_actions = int(base.action_spec.space.n)
    hidden, mlp = int(cfg.baseline.hidden), tuple(cfg.heads.hidden)
    net, gru = make_recurrent_qnet(obs_dim, num_actions, hidden, mlp, cfg.heads.activation)
    net = net.to(cfg.device)
    env = TransformedEnv(base, recurrent_transforms(gru, num_actions))
    spec = BaselineSpec("recurrent", obs_dim, num_actions, mlp, hidden=hidden)
    learner = BaselineLearner(net, env.action_spec, cfg, True, time_major=False)
    return RecurrentAgent(cfg, seed, spec, BaselineController(net, spec), learner, env)


def learning_phase(agent: RecurrentAgent) -> dict[str, float]:
    """One epsilon-greedy episode per sub-environment (training instances), stored whole, then the
    gradient steps its frames called for (module docstring); returns the mean items per episode,
    the frames played and the CPU seconds of the updates."""
    t = agent.cfg.train
    env = agent.env
    n = env.batch_size[0]
    num_actions = agent.spec.num_actions
    store = stored_keys("recurrent")
    td = env.reset()
    alive = torch.ones(n, dtype=torch.bool, device=env.device)
    items = torch.zeros(n, device=env.device)
    steps, masks, frames, due = [], [], 0, 0
    for _ in range(env.base_env.horizon):
        greedy = agent.controller(td).get(keys.ACTION)
        explore = torch.rand(n, device=env.device) < epsilon_at(agent.frames, t)
        random = torch.randint(num_actions, (n,), device=env.device)
        td.set(keys.ACTION, torch.where(explore, random, greedy))
        td = env.step(td)
        steps.append(td.select(*store, strict=False))
        masks.append(alive)
        live = int(alive.sum())
        frames += live
        agent.frames += live
        agent.pending += live
        while agent.pending >= t.frames_per_batch:  # learn_due's schedule, kept for later
            agent.pending -= t.frames_per_batch
            due += agent.learner.updates_per_batch if agent.frames >= t.init_random_frames else 0
        items += torch.where(alive, td.get((keys.NEXT, keys.REWARD)).reshape(n), 0.0)
        alive = alive & ~td.get((keys.NEXT, keys.DONE)).reshape(n)
        if not bool(alive.any()):
            break
        td = step_mdp(td, keep_other=True)
    # (sub-env, time) in row-major order: each episode's live steps contiguous, ending at its done
    agent.learner.store(torch.stack(steps, 1)[torch.stack(masks, 1)])
    tick = time.process_time()
    if len(agent.learner.buffer) >= t.batch_size:
        update_phase(agent.learner, agent.learner.sample, due, lr_at(agent.frames, t))
        agent.updates += due
    return {
        "learn_items": float(items.mean()),
        "frames": frames,
        "update_seconds": time.process_time() - tick,
    }


def test_phase(agent: RecurrentAgent, trial: int) -> tuple[float, float]:
    """Mean items per episode (greedy, learning off) on trial ``trial``'s nominal and held-out
    seeds, in one batch of the episode player."""
    cfg, k = agent.cfg, agent.cfg.experiment.test_episodes_per_trial
    nominal, heldout = trial_seeds(k, trial)
    point = EvalPoint("", None, cfg, WargusInstances(seeds=nominal + heldout))
    ctrl = BaselineController(agent.learner.eval_net, agent.spec)  # train.eval_ema_tau's weights
    played = play(ctrl, point, 2 * k, agent.seed, 2 * k)
    items = torch.as_tensor(played["return"]).reshape(2, k).mean(1)  # torch's float32 mean
    return float(items[0]), float(items[1])


def run_recurrent_repetition(
    cfg: Config, rep: int, out_dir: str | os.PathLike, on_trial: Callable[[int, int], None] | None
) -> dict[str, Any]:
    """Repetition ``rep``'s recurrent agent through every trial; saves ``rep{rep}/recurrent.pt``.
    Returns ``items``, ``heldout_items``, ``learn_items``, ``frames``, ``updates`` ``(T,)``,
    ``cpu_seconds`` per :data:`PHASES` and ``seconds``.
    """
    start = time.perf_counter()
    seed = repetition_seed(cfg, rep)
    rep_cfg = dataclasses.replace(cfg, seed=seed)
    rows: dict[str, list] = {
        k: [] for k in ("items", "heldout_items", "learn_items", "frames", "updates")
    }
    cpu = dict.fromkeys(PHASES, 0.0)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed + RECURRENT_OFFSET)
        agent = make_recurrent_agent(rep_cfg, seed)
        for trial in range(cfg.experiment.trials):
            tick = time.process_time()
            learned = learning_phase(agent)
            cpu["updates"] += learned["update_seconds"]
            cpu["learning_loop"] += time.process_time() - tick - learned["update_seconds"]
            tick = time.process_time()
            nominal, heldout = test_phase(agent, trial)
            cpu["test"] += time.process_time() - tick
            for key, v in (
                ("items", nominal),
                ("heldout_items", heldout),
                ("learn_items", learned["learn_items"]),
                ("frames", learned["frames"]),
                ("updates", agent.updates),
            ):
                rows[key].append(v)
            if on_trial is not None:
                on_trial(rep, trial)
    net = agent.learner.eval_net
    if non_finite({"weights": net.parameters()}):
        raise ValueError(f"repetition {rep}'s recurrent agent diverged (non-finite weights)")
    save_baseline(
        baseline_path(Path(out_dir) / f"rep{rep}" / "final.pt", "recurrent"),
        net,
        agent.spec,
        rep_cfg,
        counters={"frames": agent.frames, "updates": agent.updates, "trials": len(rows["items"])},
    )
    result: dict[str, Any] = {k: np.asarray(v) for k, v in rows.items()}
    result["cpu_seconds"] = cpu
    result["seconds"] = time.perf_counter() - start
    return result


def run_recurrent_batch(
    cfg: Config,
    reps: Sequence[int],
    out_dir: str | os.PathLike,
    on_trial: Callable[[int, int], None] | None = None,
) -> list[dict[str, Any]]:
    """:func:`run_recurrent_repetition` of each of ``reps`` in turn (the shape of
    ``wargus_fig4.run_repetitions_batched``, so ``run_repetitions`` spreads them over workers)."""
    return [run_recurrent_repetition(cfg, rep, out_dir, on_trial) for rep in reps]


__all__ = [
    "PHASES",
    "RECURRENT_OFFSET",
    "RecurrentAgent",
    "learning_phase",
    "make_recurrent_agent",
    "run_recurrent_batch",
    "run_recurrent_repetition",
    "test_phase",
]
