"""Multi-step targets of the averaging and option heads, from the behaviour that ran them.

With ``train.n_step = n`` a transition's target sums up to ``n`` real rewards before it bootstraps,
where the behaviour ran that head's own policy (docs/scale.md): the averaging head (§3.1) on
averaging-mode transitions, option o's head (§3.2) on transitions where o ran, with its subtask
reward and beta_o:

    y = sum_j gamma^j r_{t+j} + gamma^k (1 - terminated) max_a Q(s_{t+k}, a)

Other pairs keep one-step targets. A window stops at the episode's end, the option's termination, a
change of behaviour mode and the batch's end; exploratory actions are kept (uncorrected,
Peng-style). :func:`nstep_returns` computes it once per collected batch.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.subtasks.base import Subtasks

NSTEP = "nstep"
"""Replay key of the window quantities (a sub-tensordict)."""


def nstep_returns(
    batch: TensorDictBase, subtasks: Subtasks, gamma: float, n: int, mode_key: str = "behaviour"
) -> TensorDictBase:
    """Add ``("nstep", ...)`` to a collector batch ``(N, T)`` in place and return it.

    Keys: ``observation (N, T, D)`` (``s_{t+k}``), ``reward (N, T)`` and ``subtask_reward (N, T,
    O)`` (discounted sums), ``discount (N, T)`` (``gamma^k``), ``terminated (N, T)``, ``beta (N, T,
    O)`` (at ``s_{t+k}``), ``steps (N, T)`` int64 (``k``).
    """
    N, T = batch.shape
    nxt = batch.get(keys.NEXT)
    flat = batch.reshape(-1)
    sub_r = subtasks.reward(flat).to(torch.float32).reshape(N, T, -1)  # (N, T, O)
    beta = subtasks.termination(flat.get(keys.NEXT)).reshape(N, T, -1)  # (N, T, O) bool
    reward = nxt.get(keys.REWARD).reshape(N, T).to(torch.float32)
    terminated = nxt.get(keys.TERMINATED).reshape(N, T)
    done = nxt.get(keys.DONE).reshape(N, T)
    mode = batch.get(mode_key).reshape(N, T)  # (N, T) int64, -1 averaging, o >= 0 option o
    next_obs = nxt.get(keys.OBSERVATION)  # (N, T, D)
    num_options = sub_r.shape[-1]
    # the running option's termination ends a window (averaging mode: never)
    stop_beta = beta.gather(-1, mode.clamp_min(0).unsqueeze(-1)).squeeze(-1) & (mode >= 0)

    R = torch.zeros(N, T, device=reward.device)
    R_sub = torch.zeros(N, T, num_options, device=reward.device)
    disc = torch.ones(N, T, device=reward.device)
    steps = torch.zeros(N, T, dtype=torch.int64, device=reward.device)
    last = torch.arange(T, device=reward.device).expand(N, T).clone()  # index of the last step
    alive = torch.ones(N, T, dtype=torch.bool, device=reward.device)
    t_idx = torch.arange(T, device=reward.device)
    for j in range(int(n)):
        src = (t_idx + j).clamp_max(T - 1)  # (T,) step t+j (clamped; masked below)
        valid = alive & (t_idx + j < T).unsqueeze(0) & (mode[:, src] == mode)
        vf = valid.to(torch.float32)
        R = R + vf * disc * reward[:, src]
        R_sub = R_sub + (vf * disc).unsqueeze(-1) * sub_r[:, src]
        disc = torch.where(valid, disc * gamma, disc)
        steps = steps + valid.to(torch.int64)
        last = torch.where(valid, src.unsqueeze(0).expand(N, T), last)
        alive = valid & ~done[:, src] & ~stop_beta[:, src]
    gather = last.unsqueeze(-1)
    out = {
        "observation": next_obs.gather(1, gather.expand(N, T, next_obs.shape[-1])),
        "reward": R,
        "subtask_reward": R_sub,
        "discount": disc,
        "terminated": terminated.gather(1, last),
        "beta": beta.gather(1, gather.expand(N, T, num_options)),
        "steps": steps,
    }
    for k, v in out.items():
        batch.set((NSTEP, k), v)
    return batch
