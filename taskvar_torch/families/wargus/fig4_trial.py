"""One trial of the Wargus Figure 4 protocol (paper §3.5.1; docs/wargus-fig4.md): the learning
phase (:func:`learning_phase`, :func:`learning_phases`) and the test phase (:func:`test_phase`,
:func:`test_trials`), stepping the pure dynamics through ``reset_all``/``step_all``
(docs/benchmarks.md); the TorchRL loops they equal are in
``benchmarks/reference/wargus_torchrl_trial.py``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from taskvar_torch import keys
from taskvar_torch.config import METHODS, Config
from taskvar_torch.contract import HELDOUT_SEEDS
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.families.wargus.dynamics import ITEM_LOST, NOMINAL_SEEDS
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.heads.behaviour import BEHAVIOUR, IS_INIT, BehaviourPolicy
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.training.learning import epsilon_at, learning_started, update_phase

# --------------------------------------------------------------------------------------------
# the agent: every head, one learner, one replay buffer (paper §3.5.1: no prior knowledge)


@dataclasses.dataclass
class LifelongAgent:
    """Everything one repetition learns, from scratch, plus its counters."""

    cfg: Config
    heads: Any
    subtasks: Any
    learner: Any
    behaviour: BehaviourPolicy
    buffer: Any
    replay_generator: torch.Generator
    first_visit: FirstVisitFilter
    explore_generator: torch.Generator | None = None  # the behaviour's draws (own stream)
    frames: int = 0
    pending: int = 0  # frames stored since the last update phase
    updates: int = 0
    update_seconds: float = 0.0  # CPU seconds (``time.process_time``) spent in gradient updates


def learn_due(agent: LifelongAgent, t: Any) -> None:
    """``train.updates_per_batch`` updates (one shared sample each) per ``train.frames_per_batch``
    frames played, at ``train.lr``; their CPU time goes to ``agent.update_seconds``.
    """
    while agent.pending >= t.frames_per_batch:
        agent.pending -= t.frames_per_batch
        if learning_started(agent.frames, len(agent.buffer), t):
            start = time.process_time()
            update_phase(agent.learner, agent.buffer.sample, t.updates_per_batch)
            agent.updates += t.updates_per_batch
            agent.update_seconds += time.process_time() - start


# --------------------------------------------------------------------------------------------
# one trial: learning phase, then test phase


def repetition_seed(cfg: Config, rep: int) -> int:
    """Seed of repetition ``rep``: ``cfg.seed + rep`` (networks, envs, replay, exploration)."""
    return int(cfg.seed) + int(rep)


def nominal_seeds(k: int) -> tuple[int, ...]:
    """The ``k`` fixed test instance seeds: :data:`NOMINAL_SEEDS`, extended by consecutive ints."""
    extra = tuple(
        range(max(NOMINAL_SEEDS) + 1, max(NOMINAL_SEEDS) + 1 + max(k - len(NOMINAL_SEEDS), 0))
    )
    return (NOMINAL_SEEDS + extra)[:k]


def trial_seeds(k: int, trial: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Instance seeds of trial ``trial``'s ``k`` test episodes: nominal ``(j + trial) % k`` and
    held-out ``HELDOUT_SEEDS[(trial k + j) % len]``, the same for every method."""
    seeds, n = nominal_seeds(k), len(HELDOUT_SEEDS)
    nominal = tuple(seeds[(j + trial) % k] for j in range(k))
    return nominal, tuple(HELDOUT_SEEDS[(trial * k + j) % n] for j in range(k))


def learning_phase(agent: LifelongAgent, env: WargusEnv) -> dict[str, float]:
    """One episode per sub-env (training instances), learning on (paper §3.5.1); returns mean items
    per episode and frames played. :func:`learning_phases` with one agent.
    """
    return learning_phases([agent], env, agent.behaviour, agent.first_visit)[0]


def learning_phases(
    agents: Sequence[LifelongAgent],
    env: WargusEnv,
    behaviour: BehaviourPolicy,
    first_visit: FirstVisitFilter,
    on_update: Callable[[int], None] | None = None,
) -> list[dict[str, float]]:
    """:func:`learning_phase` of ``S = len(agents)`` repetitions in one loop: seed-major blocks of
    ``env``, one stacked behaviour pass, each repetition with its own generator, epsilon, counters,
    replay and learner; ``on_update(s)`` follows repetition ``s``'s update phase.
    """
    S = len(agents)
    t = agents[0].cfg.train
    N = env.num_envs
    n = N // S
    dev = env.device
    td = env.reset_all()  # every sub-env starts a new episode with a fresh training instance
    td.set(IS_INIT, torch.ones(N, 1, dtype=torch.bool, device=dev))
    not_init = torch.zeros(N, 1, dtype=torch.bool, device=dev)
    if t.first_visit:
        first_visit.clear()
    alive = torch.ones(N, dtype=torch.bool, device=dev)
    items = torch.zeros(N, device=dev)
    frames = [0] * S
    staged: list[TensorDictBase] = []  # transitions of this update phase, not yet in the buffers
    masks: list[torch.Tensor] = []  # (N,) which of them to keep
    for _ in range(env.horizon):
        live = [int(alive.sum())] if S == 1 else alive.view(S, n).sum(1).tolist()
        eps = [epsilon_at(a.frames, t) for a in agents]
        if S == 1:
            behaviour.set_epsilon(eps[0])
        else:  # a repetition whose episodes all ended stops drawing, as it would alone
            behaviour.set_epsilon(torch.tensor(eps, device=dev).repeat_interleave(n))
            behaviour.set_active([k > 0 for k in live])
        td = behaviour(td)
        action = td.get(keys.ACTION)
        nxt = env.step_all(action)
        nxt.set(IS_INIT, not_init)
        # ---- stage this step's transitions of the live episodes (first visits: at the flush) --
        staged.append(_transition(td, nxt))
        masks.append(alive)
        for s, agent in enumerate(agents):
            agent.frames += live[s]
            agent.pending += live[s]
            frames[s] += live[s]
        items += torch.where(alive, nxt.get(keys.REWARD).reshape(N), 0.0)
        # ---- learn: each repetition, every head from one shared sample per update -----------
        if any(a.pending >= t.frames_per_batch for a in agents):
            _flush(agents, staged, masks, first_visit, t.first_visit)
        for s, agent in enumerate(agents):
            if not live[s]:
                continue  # its phase is over: it learns nothing more until it would alone
            before = agent.updates
            learn_due(agent, t)
            if on_update is not None and agent.updates != before:
                on_update(s)
        alive = alive & ~nxt.get(keys.DONE).reshape(N)
        if not bool(alive.any()):
            break
        nxt.set(BEHAVIOUR, td.get(BEHAVIOUR))  # carried, like step_mdp(keep_other=True)
        td = nxt
    _flush(agents, staged, masks, first_visit, t.first_visit)
    per_block = items.view(S, n).mean(1).tolist()
    return [{"learn_items": per_block[s], "frames": frames[s]} for s in range(S)]


_HIDDEN = (keys.INSTANCE, keys.REWARD)  # never replayed / not part of a state


def _transition(td: TensorDictBase, nxt: TensorDictBase) -> TensorDictBase:
    """The replayed transition: the state ``td`` (with action, behaviour, ``is_init``) and
    ``"next"``, minus the hidden instance (the keys ``env.step`` + ``step_mdp`` give)."""
    root = {k: v for k, v in td.items() if k not in _HIDDEN}
    root[keys.NEXT] = nxt.exclude(keys.INSTANCE)
    return TensorDict._new_unsafe(root, batch_size=td.batch_size, device=td.device)


def _flush(
    agents: Sequence[LifelongAgent],
    staged: list,
    masks: list,
    first_visit: FirstVisitFilter,
    use_first_visit: bool,
) -> None:
    """Write the kept staged transitions of live episodes to each block's replay (first visits only
    with ``use_first_visit``), in step order.
    """
    if not staged:
        return
    batch = torch.cat(staged)  # (T N,) step-major
    keep = torch.cat(masks)
    T, N = len(staged), staged[0].shape[0]
    if use_first_visit:
        obs = batch.get(keys.OBSERVATION).view(T, N, -1)
        keep = keep & first_visit.visit_steps(obs, batch.get(keys.ACTION).view(T, N)).view(-1)
    S = len(agents)
    if S == 1:
        if bool(keep.any()):
            agents[0].buffer.extend(batch[keep])
    else:
        block = torch.arange(N, device=keep.device).div(N // S, rounding_mode="floor").repeat(T)
        for s, agent in enumerate(agents):
            rows = keep & (block == s)
            if bool(rows.any()):
                agent.buffer.extend(batch[rows])
    staged.clear()
    masks.clear()


def test_phase(policy: SideBySide, env: WargusEnv, k: int) -> dict[str, np.ndarray]:
    """The nominal test episodes of every method side by side, learning off (paper §3.5.1): per
    method ``items``, ``interruptions`` and the hierarchy's steps per controlling subtask."""
    return test_trials(policy, env, k, None)[0]


@torch.inference_mode()
def test_trials(
    policy: SideBySide,
    env: WargusEnv,
    k: int,
    snapshots: Sequence[Sequence[torch.Tensor]] | None,
    calibrations: Sequence[RobustnessCalibration | None] | None = None,
) -> list[dict[str, np.ndarray]]:
    """Test phases of ``G`` trials side by side, trial ``g`` on frozen heads ``snapshots[g]``
    (``None``: the live heads) on rows ``(g, method, episode)``; one :func:`test_phase` result per
    trial."""
    params = None
    G = 1
    if snapshots is not None:
        params = [torch.stack(p) for p in zip(*snapshots)]
        G = len(snapshots)
    M = len(METHODS)
    n = env.num_envs
    if n != G * M * k:
        raise ValueError(f"the test env has {n} sub-environments, expected {G} x {M} x {k}")
    dev = env.device
    td = env.reset_all()
    running = torch.full((n,), -1, dtype=torch.int64, device=dev)
    alive = torch.ones(n, dtype=torch.bool, device=dev)
    ret = torch.zeros(n, device=dev)
    inter = torch.zeros(n, dtype=torch.int64, device=dev)
    lost = torch.zeros(n, dtype=torch.int64, device=dev)
    h = METHODS.index("hierarchy")
    thresholds = policy.threshold_rows(calibrations) if calibrations is not None else None
    options, alives = [], []
    for _ in range(env.horizon):
        lost += (
            td.get(ITEM_LOST).reshape(n) & alive
        ).long()  # the step that led here lost the item
        out = policy.decide_batch(td, running, params, thresholds)
        inter += (out[keys.INTERRUPTED] & alive).long()
        options.append(out[keys.OPTION])
        alives.append(alive)
        td = env.step_all(out[keys.ACTION])
        running = out["next_running"]
        ret += torch.where(alive, td.get(keys.REWARD).reshape(n), 0.0)
        alive = alive & ~td.get(keys.DONE).reshape(n)
        if not bool(alive.any()):
            break
    option = torch.stack(options, -1).view(G, M, k, -1)[:, h]  # (G, K, T)
    live = torch.stack(alives, -1).view(G, M, k, -1)[:, h]  # (G, K, T)
    ret, inter, lost = ret.view(G, M * k), inter.view(G, M * k), lost.view(G, M * k)
    return [
        _test_summary(policy, ret[g], inter[g], option[g], live[g], k, lost[g]) for g in range(G)
    ]


def _test_summary(
    policy: SideBySide,
    ret: torch.Tensor,  # (M K,) items per test episode
    inter: torch.Tensor,  # (M K,) interruptions per test episode
    option: torch.Tensor,  # (K, T) the hierarchy's option per step
    alive: torch.Tensor,  # (K, T) its live steps
    k: int,
    lost: torch.Tensor,  # (M K,) item_lost events per test episode
) -> dict[str, np.ndarray]:
    num_options = len(policy.controllers[METHODS.index("hierarchy")].heads.option_names)
    control = torch.stack([((option == o) & alive).sum() for o in range(num_options)])
    return {
        "items": ret.reshape(len(METHODS), k).mean(-1).cpu().numpy(),  # (M,)
        "interruptions": inter.reshape(len(METHODS), k).double().mean(-1).cpu().numpy(),  # (M,)
        "control_steps": control.cpu().numpy(),  # (O,)
        "item_lost": lost.reshape(len(METHODS), k).double().mean(-1).cpu().numpy(),  # (M,)
    }


__all__ = [
    "LifelongAgent",
    "nominal_seeds",
    "repetition_seed",
    "trial_seeds",
    "learn_due",
    "learning_phase",
    "learning_phases",
    "test_phase",
    "test_trials",
]
