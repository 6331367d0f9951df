"""Batched evaluation episodes: :func:`run_episodes` plays one episode in each of N sub-environments
with any TorchRL policy. Two calls on envs of the same ``seed`` are paired (same instance, start and
noise per episode, :mod:`taskvar_torch.rng`); another ``noise_seed`` redraws the noise only.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import step_mdp

from taskvar_torch import keys


@torch.inference_mode()
def run_episodes(
    env: EnvBase,
    policy,
    max_steps: int | None = None,
    trace_keys: tuple = (),
    on_step: Callable[[TensorDictBase, torch.Tensor], None] | None = None,
) -> TensorDictBase:
    """Play one episode per sub-environment of ``env`` (batch ``[N]``) with ``policy``.

    Returns a ``[N]`` tensordict: ``return``, ``length``, ``start``, ``("instance", ...)``,
    ``interruptions`` and, per key in ``trace_keys``, a ``(N, T)`` trace ``("trace", key)`` with
    ``("trace", "alive")``. ``on_step(td, alive)`` is called after each ``env.step``.
    """
    td = env.reset()
    n = env.batch_size[0]
    horizon = max_steps if max_steps is not None else int(getattr(env, "horizon", 1000))
    ret = torch.zeros(n, device=env.device)
    length = torch.zeros(n, dtype=torch.int64, device=env.device)
    interruptions = torch.zeros(n, dtype=torch.int64, device=env.device)
    alive = torch.ones(n, dtype=torch.bool, device=env.device)
    start = td.get(keys.CELL, None)
    start = start.clone() if start is not None else None
    instance = td.get(keys.INSTANCE).clone()
    traces: dict = {k: [] for k in trace_keys}
    alive_trace = []
    for _ in range(horizon):
        td = policy(td)
        if keys.INTERRUPTED in td.keys():
            interruptions += (td.get(keys.INTERRUPTED).reshape(n) & alive).long()
        for k in trace_keys:
            traces[k].append(td.get(k).reshape(n).clone())
        alive_trace.append(alive.clone())
        td = env.step(td)
        if on_step is not None:
            on_step(td, alive.clone())
        reward = td.get((keys.NEXT, keys.REWARD)).reshape(n)
        ret += torch.where(alive, reward, torch.zeros_like(reward))
        length += alive.long()
        alive &= ~td.get((keys.NEXT, keys.DONE)).reshape(n)
        if not bool(alive.any()):
            break
        td = step_mdp(td, keep_other=True)
    out = TensorDict(
        {"return": ret, "length": length, "interruptions": interruptions, keys.INSTANCE: instance},
        batch_size=[n],
        device=env.device,
    )
    if start is not None:
        out.set("start", start)
    if trace_keys:
        tr = {k: torch.stack(v, -1) for k, v in traces.items()}
        tr["alive"] = torch.stack(alive_trace, -1)
        out.set("trace", TensorDict(tr, batch_size=[n], device=env.device))
    return out


__all__ = ["run_episodes"]
