"""The TorchRL loops of one Wargus Figure 4 trial, kept to measure and test against, not part of
the library (issue 57): ``learning_phase_torchrl`` and ``test_phase_torchrl`` play a trial through
TorchRL's ``EnvBase.step``, ``step_mdp`` and :func:`~taskvar_torch.run_episodes`, the reference
``tests/families/wargus/test_wargus_fast_loop.py`` checks the library's fast loops
(:mod:`taskvar_torch.families.wargus.fig4_trial`) bit-equal to and ``benchmarks/wargus_trial.py``
times them against."""

from __future__ import annotations

import numpy as np
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import step_mdp

from taskvar_torch import keys
from taskvar_torch.config import METHODS
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.experiments.evaluation import run_episodes
from taskvar_torch.families.wargus.dynamics import ITEM_LOST
from taskvar_torch.families.wargus.fig4_trial import (  # the fast loop's own summary
    LifelongAgent,
    _test_summary,
    learn_due,
)
from taskvar_torch.training.learning import epsilon_at


def learning_phase_torchrl(agent: LifelongAgent, env: TransformedEnv) -> dict[str, float]:
    """``fig4_trial.learning_phase`` through TorchRL's ``EnvBase.step`` (``env``: the learning env
    with an ``InitTracker``), ``step_mdp`` and one ``extend`` per step: the reference loop."""
    t = agent.cfg.train
    n = env.batch_size[0]
    td = env.reset()  # every sub-env starts a new episode with a fresh training instance
    alive = torch.ones(n, dtype=torch.bool, device=env.device)
    items = torch.zeros(n, device=env.device)
    frames = 0
    drop = (keys.INSTANCE, (keys.NEXT, keys.INSTANCE))
    for _ in range(env.base_env.horizon):
        agent.behaviour.set_epsilon(epsilon_at(agent.frames, t))
        td = agent.behaviour(td)
        td = env.step(td)
        keep = alive
        if t.first_visit:
            keep = keep & agent.first_visit(td.unsqueeze(1)).squeeze(1)
        if bool(keep.any()):
            agent.buffer.extend(td.exclude(*drop)[keep])
        n_alive = int(alive.sum())
        agent.frames += n_alive
        agent.pending += n_alive
        frames += n_alive
        items += torch.where(alive, td.get((keys.NEXT, keys.REWARD)).reshape(n), 0.0)
        learn_due(agent, t)
        alive = alive & ~td.get((keys.NEXT, keys.DONE)).reshape(n)
        if not bool(alive.any()):
            break
        td = step_mdp(td, keep_other=True)
    return {"learn_items": float(items.mean()), "frames": frames}


def test_phase_torchrl(policy: SideBySide, env: TransformedEnv, k: int) -> dict[str, np.ndarray]:
    """``fig4_trial.test_phase`` through :func:`~taskvar_torch.run_episodes` (``env``: the test env with the
    controllers' primer): the reference implementation."""
    out = run_episodes(env, policy, trace_keys=(keys.OPTION, ITEM_LOST))
    h = METHODS.index("hierarchy")
    option = out["trace", keys.OPTION][h * k : (h + 1) * k]  # (K, T)
    alive = out["trace", "alive"][h * k : (h + 1) * k]  # (K, T)
    lost = (out["trace", ITEM_LOST] & out["trace", "alive"]).sum(-1)  # (M K,)
    return _test_summary(policy, out["return"], out["interruptions"], option, alive, k, lost)
