"""A fresh agent of the Wargus Figure 4 protocol (paper §3.5.1; docs/wargus-fig4.md): networks,
replay and exploration generator, the test envs, the four methods' test controllers and the
hierarchy's calibration after a trial.
"""

from __future__ import annotations

from typing import Any

import torch
from torchrl.envs import TransformedEnv

from taskvar_torch import keys
from taskvar_torch.config import Config
from taskvar_torch.controllers import Controller
from taskvar_torch.factory import (
    build_heads,
    calibrate,
    make_env,
    make_learner,
    make_method_controller,
    make_subtasks,
    replay_states,
)
from taskvar_torch.families.wargus.dynamics import WargusInstances
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.fig4_metrics import (
    METHODS,
)
from taskvar_torch.families.wargus.fig4_trial import (
    LifelongAgent,
    trial_seeds,
)
from taskvar_torch.heads.behaviour import BehaviourPolicy
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.training.replay import make_replay_buffer

EXPLORATION_OFFSET = 1 << 32
"""A repetition's exploration generator is seeded ``seed + EXPLORATION_OFFSET``."""


# --------------------------------------------------------------------------------------------
# a fresh agent (paper §3.5.1: no prior knowledge), its test env and test controllers


def exploration_generator(seed: int) -> torch.Generator:
    """The behaviour's own random stream of the repetition seeded ``seed`` (option picks,
    exploration, option episodes, epsilon-greedy actions): ``seed + EXPLORATION_OFFSET``, apart
    from every replay generator (``seed + 1``)."""
    return torch.Generator(device="cpu").manual_seed(int(seed) + EXPLORATION_OFFSET)


def make_behaviour(
    cfg: Config, heads: Any, subtasks: Any, action_spec: Any, generators: list[torch.Generator]
) -> BehaviourPolicy:
    """The behaviour policy of ``heads`` (one repetition's, or several stacked), drawing block
    ``s`` of its rows from ``generators[s]``."""
    return BehaviourPolicy(
        heads,
        subtasks,
        action_spec,
        option_prob=cfg.train.option_behaviour_prob,
        root_policy=cfg.train.hierarchy_root_policy,
        compile=cfg.train.compile,
        generators=generators,
    )


def make_agent(cfg: Config, env: WargusEnv | TransformedEnv, seed: int) -> LifelongAgent:
    """Fresh heads, learner, behaviour policy and an empty replay buffer (seeded by ``seed``:
    the networks' initialisation from the global stream, the replay sampler and the behaviour
    from their own generators)."""
    subtasks = make_subtasks(cfg, getattr(env, "base_env", env))
    heads = build_heads(cfg, env, subtasks)
    learner = make_learner(cfg, heads, subtasks)
    explore = exploration_generator(seed)
    behaviour = make_behaviour(cfg, heads, subtasks, env.action_spec, [explore])
    generator = torch.Generator(device="cpu").manual_seed(seed + 1)
    obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
    return LifelongAgent(
        cfg=cfg,
        heads=heads,
        subtasks=subtasks,
        learner=learner,
        behaviour=behaviour,
        buffer=make_replay_buffer(cfg, generator),
        replay_generator=generator,
        first_visit=FirstVisitFilter(env.batch_size.numel(), obs_dim, device=cfg.device),
        explore_generator=explore,
    )


def make_test_env(
    cfg: Config, k: int, seed: int, first_trial: int = 0, trials: int = 1
) -> WargusEnv:
    """Test env of ``trials`` trials from ``first_trial``: rows ``(g, method, j)``, episode ``j`` of
    trial ``t`` playing nominal seed ``(j + t) % k``; with ``trials = 1`` each reset is the next
    trial."""
    rows = tuple(
        s for g in range(trials) for _ in METHODS for s in trial_seeds(k, first_trial + g)[0]
    )
    return make_env(
        cfg, len(rows), seed=seed, instances=WargusInstances(seeds=rows), validate_actions=False
    )


def make_heldout_test_env(
    cfg: Config, k: int, seed: int, first_trial: int = 0, trials: int = 1
) -> WargusEnv:
    """:func:`make_test_env` on the sealed held-out instances: episode ``j`` of trial ``t`` plays
    ``HELDOUT_SEEDS[(t k + j) % len(HELDOUT_SEEDS)]``, the same seed for every method (paired), so
    the trials walk through every held-out instance in turn."""
    rows = tuple(
        s for g in range(trials) for _ in METHODS for s in trial_seeds(k, first_trial + g)[1]
    )
    return make_env(
        cfg, len(rows), seed=seed, instances=WargusInstances(seeds=rows), validate_actions=False
    )


def make_test_controllers(agent: LifelongAgent) -> list[Controller]:
    """The four methods on the agent's live heads (paper §3.5.2), in :data:`METHODS` order. The
    hierarchy's calibration (``train.robustness_threshold = "calibrated"``) is set per trial from
    the replay (:func:`trial_calibration`)."""
    cal = None
    if agent.cfg.train.robustness_threshold == "calibrated":  # placeholder until the first trial
        O = agent.subtasks.num_options  # noqa: E741
        cal = RobustnessCalibration(
            torch.full((O,), agent.cfg.train.robustness_tau), torch.ones(O)
        ).to(agent.cfg.device)
    return [
        make_method_controller(agent.cfg, m, agent.heads, agent.subtasks, calibration=cal)
        for m in METHODS
    ]


def trial_calibration(agent: LifelongAgent) -> RobustnessCalibration | None:
    """The hierarchy's thresholds after a trial, on training states of the replay (never the
    nominal test seeds); ``None`` with ``train.robustness_threshold = "fixed"``."""
    if agent.cfg.train.robustness_threshold != "calibrated" or len(agent.buffer) == 0:
        return None
    return calibrate(agent.cfg, agent.heads, agent.subtasks, replay_states(agent.buffer))


__all__ = [
    "EXPLORATION_OFFSET",
    "exploration_generator",
    "make_agent",
    "make_behaviour",
    "make_heldout_test_env",
    "make_test_controllers",
    "make_test_env",
    "trial_calibration",
]
