"""Batched evaluation episodes: :func:`run_episodes` plays exactly one episode in each of N
sub-environments with any TorchRL policy (a controller with carried state included) and returns
per-episode figures. Two calls on envs built with the same ``seed`` are *paired*: the same
instance, start cell and gust stream per episode (common random numbers, see ``rng.py``); a
different ``noise_seed`` keeps the instance and start but redraws the gusts (the null comparison).

It sits with the envs, below the controllers' calibration (``factory.training_states``) and the
experiments, which all play through it; :mod:`taskvar_torch.experiments.evaluation` hands it on
with the statistics experiments report.
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

    Returns a ``[N]`` tensordict: ``return`` (undiscounted), ``length``, ``start`` (first cell),
    ``("instance", ...)`` (the episode's instance), ``interruptions`` (count of steps whose
    ``keys.INTERRUPTED`` flag was set, when the policy writes it) and, for each key in
    ``trace_keys``, a ``(N, T)`` per-step trace (``("trace", key)``) plus ``("trace", "alive")``.
    ``on_step(td, alive)``: called after each ``env.step`` with the step's tensordict (the state
    acted in and the policy's outputs at the root, the transition under ``"next"``) and the
    ``(N,)`` mask of the episodes still running at that step.
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
