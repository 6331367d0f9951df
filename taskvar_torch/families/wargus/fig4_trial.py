"""One trial of the Wargus Figure 4 protocol: a learning phase, then a test phase (paper §3.5.1;
docs/wargus-fig4.md). The protocol around it (agent construction, repetitions, results) is
:mod:`taskvar_torch.families.wargus.fig4`, which re-exports every name here.

* :class:`LifelongAgent` holds what one repetition learns (every head, one learner, one replay
  buffer) and its counters; :func:`learn_due` takes the gradient steps the frames played call for.
* :func:`learning_phase`: one episode per sub-environment of the training instance distribution,
  learning on; :func:`learning_phases`: several repetitions' at once, in one loop (each still
  learning exactly what it learns alone).
* :func:`test_phase` / :func:`test_trials`: the nominal test episodes of every method side by side,
  learning off.

Speed (docs/benchmarks.md, ``benchmarks/wargus_trial.py``): the loops step the pure dynamics
through :meth:`WargusEnv.reset_all` / :meth:`WargusEnv.step_all` (no ``EnvBase`` checks,
transforms or ``step_mdp``), write replay once per update phase, run every head in one stacked
pass (:class:`~taskvar_torch.heads.snapshots.HeadValues`), and test several trials
(:data:`~taskvar_torch.families.wargus.fig4_repetition.TEST_GROUP`) side by side on frozen copies of their
heads (:func:`test_trials` with :class:`~taskvar_torch.controllers.side_by_side.SideBySide`). The
TorchRL loops they are tested bit-equal to live in ``benchmarks/reference/wargus_torchrl_trial.py``.
``train.compile`` also runs the behaviour's choices, the dynamics step and the learner's losses
through ``torch.compile`` (``taskvar_torch/compiling.py``).
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
    """``train.updates_per_batch`` updates for every ``train.frames_per_batch`` frames played (after
    ``train.init_random_frames``: :func:`~taskvar_torch.training.learning.learning_started`), each on one
    shared sample for every head (:func:`~taskvar_torch.training.learning.update_phase`, at the learner's
    ``train.lr``: this agent does not apply ``train.lr_end``, which no shipped config sets); their
    CPU time (sampling included) is added to ``agent.update_seconds``."""
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
    """The instance seeds of trial ``trial``'s (0-based) ``k`` test episodes, nominal and held-out:
    episode ``j`` plays nominal seed ``nominal_seeds(k)[(j + trial) % k]`` (every seed every trial)
    and held-out seed ``HELDOUT_SEEDS[(trial k + j) % len(HELDOUT_SEEDS)]`` (the trials walk
    through the sealed held-out instances in turn); every method plays the same (paired)."""
    seeds, n = nominal_seeds(k), len(HELDOUT_SEEDS)
    nominal = tuple(seeds[(j + trial) % k] for j in range(k))
    return nominal, tuple(HELDOUT_SEEDS[(trial * k + j) % n] for j in range(k))


def learning_phase(agent: LifelongAgent, env: WargusEnv) -> dict[str, float]:
    """One episode per sub-environment (training instances) with learning on (paper §3.5.1).

    Transitions of live episodes are replayed; every ``frames_per_batch`` frames played the learner
    takes ``updates_per_batch`` gradient steps on every head. Returns the mean items per episode
    and the frames played.

    The fast loop: it steps ``env``'s dynamics directly (:meth:`WargusEnv.reset_all` /
    :meth:`WargusEnv.step_all`, no ``EnvBase`` checks, transforms or ``step_mdp``), carries
    ``is_init`` and the behaviour mode itself, and filters first visits and writes the kept
    transitions to the replay buffer once per update phase (before any sample, so the buffer
    holds the same rows in the same order). Same draws, same transitions, same updates as the
    TorchRL loop ``learning_phase_torchrl`` (``benchmarks/reference/wargus_torchrl_trial.py``,
    tested equal). :func:`learning_phases` with one agent.
    """
    return learning_phases([agent], env, agent.behaviour, agent.first_visit)[0]


def learning_phases(
    agents: Sequence[LifelongAgent],
    env: WargusEnv,
    behaviour: BehaviourPolicy,
    first_visit: FirstVisitFilter,
    on_update: Callable[[int], None] | None = None,
) -> list[dict[str, float]]:
    """:func:`learning_phase` of ``S = len(agents)`` repetitions at once, in one loop.

    ``env``'s sub-environments are ``S`` seed-major blocks (:meth:`WargusEnv.set_seed_blocks`,
    block ``s`` drawing what repetition ``s``'s own env draws); ``behaviour`` acts for every block
    at once (the repetitions' heads stacked, :func:`~taskvar_torch.heads.seeds.stack_seeds`, with
    ``generators``: block ``s`` draws from repetition ``s``'s exploration generator only), each
    block at its own repetition's epsilon; ``first_visit`` has a row per sub-environment. Each
    repetition keeps its own counters, replay buffer and learner: its update phases fall where its
    own frames call for them (:func:`learn_due`), on its own samples, and ``on_update(s)`` follows
    repetition ``s``'s update phase (to copy its new weights into the acting stack). So each
    repetition plays and learns exactly what it does alone (tested equal); only the per-step work
    (behaviour, dynamics, staging) is shared.
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
    """Write the staged transitions of live episodes (``masks``) that are kept to the replay
    buffers, block ``s`` of the sub-environments to ``agents[s]``'s (one ``extend`` each, in step
    order); ``use_first_visit``: first visits only, filtered here for all the staged steps at once
    (:meth:`FirstVisitFilter.visit_steps`, equal to a visit per step). Writing a repetition's
    transitions before its own update phase is due changes nothing it samples: its buffer holds
    the same rows in the same order when it next samples."""
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
    """The nominal test episodes of every method, side by side, learning off (paper §3.5.1).

    Returns per method ``items`` (mean per test episode), ``interruptions`` (per episode) and,
    over the hierarchy's live steps, the count of steps each subtask held control. ``env``: the
    test env (:func:`~taskvar_torch.families.wargus.fig4_agent.make_test_env`), at its next trial.
    The fast loop (:func:`test_trials` with the live heads); the same episodes as TorchRL's
    (``test_phase_torchrl``, ``benchmarks/reference/wargus_torchrl_trial.py``, tested equal).
    """
    return test_trials(policy, env, k, None)[0]


@torch.inference_mode()
def test_trials(
    policy: SideBySide,
    env: WargusEnv,
    k: int,
    snapshots: Sequence[Sequence[torch.Tensor]] | None,
    calibrations: Sequence[RobustnessCalibration | None] | None = None,
) -> list[dict[str, np.ndarray]]:
    """The test phases of ``G`` trials side by side: trial ``g`` with frozen heads
    ``snapshots[g]`` (:meth:`HeadValues.snapshot`; ``None``: one trial, the live heads) on rows
    ``(g, method, episode)`` of ``env``
    (:func:`~taskvar_torch.families.wargus.fig4_agent.make_test_env` with ``trials=G``).

    Steps ``env``'s dynamics directly (:meth:`WargusEnv.step_all`) with
    :meth:`SideBySide.decide_batch`, carries ``running_option`` (-1 at the start) itself, and stops
    when every episode is done. Test episodes read nothing learnt later and draw nothing from the
    global stream, so testing a trial later, beside others, gives the episodes it gave right after
    its learning phase (tested equal). Returns one :func:`test_phase` result per trial.
    """
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
