"""A reference loop kept to measure and test against, not part of the library (issue 57):
``rollout_fast(env, policy, steps)`` steps a :class:`WindyGridEnv` the way TorchRL's ``Collector``
does, without its per-step tensordict work (``benchmarks/env_throughput.py`` times it as path c2;
``tests/families/windy/test_windy_fast_rollout.py`` checks it equals the collector bit for bit).
It reads the env's own state (``_cell``, ``_p``, ``_dir``, ``_obs_table``) and pure step."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase

from taskvar_torch import keys
from taskvar_torch.families.windy import WindyGridEnv

_FLAGS = (keys.DONE, keys.TERMINATED, keys.TRUNCATED)


@torch.no_grad()
def rollout_fast(
    env: WindyGridEnv,
    policy: Callable[[TensorDictBase], TensorDictBase],
    steps: int,
    compact_obs: bool = False,
    out: TensorDictBase | None = None,
) -> TensorDictBase:
    """``steps`` steps of every sub-env under ``policy``, resetting done sub-envs as they end.

    Returns the ``(N, steps)`` batch that TorchRL's ``Collector(env, policy,
    frames_per_batch=N * steps, track_traj_ids=False, compact_obs=compact_obs)`` yields: the
    same keys, shapes, dtypes and values (tested bit for bit), and leaves the env where the
    collector would (successive calls continue the episodes; the first starts them if the env
    was never reset). It skips the collector's per-step tensordict work (``EnvBase.step``,
    ``step_mdp``, ``maybe_reset``, per-step stacking): a step is the policy, the pure step
    (``env._advance``) and, where episodes ended, ``env._start_episodes``; observations are
    gathered once per batch unless the policy reads them (docs/benchmarks.md has the figures).

    Args:
        policy: a tensordict module reading the root keys of a step (``observation``,
            ``cell``, ``instance``, ``done``...) and writing ``action`` ``(N,)`` and any other
            ``out_keys`` (stored like the collector's policy outputs). Nothing is carried
            from step to step: recurrent policies and transforms (``InitTracker``, ``RewardSum``)
            need the collector.
        steps: time steps T of the batch.
        compact_obs: drop the ``("next", ...)`` observation keys, as the collector's option.
        out: a batch returned by an earlier call (same ``steps``, ``compact_obs`` and policy)
            to overwrite and return, as the collector's ``return_same_td=True``: fresh memory
            for every batch costs more than the writes themselves at large N.

    Examples:
        >>> from tensordict.nn import TensorDictModule
        >>> env = WindyGridEnv(num_envs=4, seed=0)
        >>> policy = TensorDictModule(lambda cell: cell % 4, ["cell"], ["action"])
        >>> batch = rollout_fast(env, policy, 16)
        >>> batch["next", "observation"].shape
        torch.Size([4, 16, 25])
        >>> batch = rollout_fast(env, policy, 16, out=batch)  # the next 16 steps, same memory
    """
    T = int(steps)
    if T < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if out is not None and tuple(out.batch_size) != (env.num_envs, T):
        raise ValueError(
            f"out has batch size {tuple(out.batch_size)}, expected ({env.num_envs}, {T})"
        )
    if not hasattr(env, "_cell"):
        env._start_episodes(None)
    N, dev = env.num_envs, env.device
    in_keys = getattr(policy, "in_keys", None)
    obs_per_step = in_keys is None or keys.OBSERVATION in in_keys
    out_keys = list(getattr(policy, "out_keys", [keys.ACTION]))
    false = torch.zeros(N, 1, dtype=torch.bool, device=dev)
    cols: dict[str, list[torch.Tensor]] = {
        k: [] for k in ("cell", "p", "dir", "next", "term", "trunc", "obs")
    }
    outs: dict = {k: [] for k in out_keys}
    for _ in range(T):
        if obs_per_step:
            root = env._out(env._cell, env._p, env._dir)
            cols["obs"].append(root.get(keys.OBSERVATION))
        else:
            instance = TensorDict._new_unsafe(
                {"p": env._p, "direction": env._dir}, batch_size=env.batch_size, device=dev
            )
            flags = dict.fromkeys(_FLAGS, false)
            root = TensorDict._new_unsafe(
                {keys.CELL: env._cell, keys.INSTANCE: instance, **flags},
                batch_size=env.batch_size,
                device=dev,
            )
        cols["cell"].append(env._cell)
        cols["p"].append(env._p)
        cols["dir"].append(env._dir)
        td = policy(root)
        for k in out_keys:
            outs[k].append(td.get(k))
        cell, terminated, truncated = env._advance(td.get(keys.ACTION).reshape(-1))
        cols["next"].append(cell)
        cols["term"].append(terminated)
        cols["trunc"].append(truncated)
        done = terminated | truncated
        if bool(done.any()):
            env._start_episodes(done)
    if out is None:
        out = _empty_batch(env, T, compact_obs, outs)
    return _fill_batch(env, out, cols, outs, compact_obs)


def _empty_batch(env: WindyGridEnv, T: int, compact_obs: bool, outs: dict) -> TensorDictBase:
    """An uninitialised ``(N, T)`` batch in the collector's layout, for :func:`rollout_fast`."""
    N, D, dev = env.num_envs, env._obs_table.shape[1], env.device

    def new(*shape, dtype=torch.int64):
        return torch.empty(N, T, *shape, dtype=dtype, device=dev)

    def step_data():
        return {
            keys.OBSERVATION: new(D, dtype=torch.float32),
            keys.CELL: new(),
            keys.INSTANCE: {"p": new(dtype=torch.float32), "direction": new()},
        }

    flags = {k: new(1, dtype=torch.bool) for k in _FLAGS}
    following = {keys.REWARD: new(1, dtype=torch.float32), **flags}
    following.update({keys.INSTANCE: {}} if compact_obs else step_data())
    batch = TensorDict(
        {**step_data(), **{k: new(1, dtype=torch.bool) for k in _FLAGS}, keys.NEXT: following},
        batch_size=(N, T),
    )
    for k, v in outs.items():
        batch.set(k, new(*v[0].shape[1:], dtype=v[0].dtype))
    batch.refine_names(..., "time")
    return batch


def _fill_batch(
    env: WindyGridEnv, batch: TensorDictBase, cols: dict, outs: dict, compact_obs: bool
) -> TensorDictBase:
    """Write :func:`rollout_fast`'s per-step columns into ``batch`` (``(N, T)``), in place."""
    N, T = batch.batch_size
    D = env._obs_table.shape[1]
    cell = torch.stack(cols["cell"], 1, out=batch.get(keys.CELL))
    if cols["obs"]:
        torch.stack(cols["obs"], 1, out=batch.get(keys.OBSERVATION))
    else:
        obs = batch.get(keys.OBSERVATION).view(N * T, D)
        torch.index_select(env._obs_table, 0, cell.view(-1), out=obs)
    for k in _FLAGS:
        batch.get(k).zero_()
    instance = batch.get(keys.INSTANCE)
    torch.stack(cols["p"], 1, out=instance.get("p"))
    torch.stack(cols["dir"], 1, out=instance.get("direction"))
    following = batch.get(keys.NEXT)
    following.get(keys.REWARD).fill_(-1.0)
    terminated = torch.stack(cols["term"], 1, out=following.get(keys.TERMINATED).view(N, T))
    truncated = torch.stack(cols["trunc"], 1, out=following.get(keys.TRUNCATED).view(N, T))
    torch.bitwise_or(terminated, truncated, out=following.get(keys.DONE).view(N, T))
    if not compact_obs:
        nxt = torch.stack(cols["next"], 1, out=following.get(keys.CELL))
        obs = following.get(keys.OBSERVATION).view(N * T, D)
        torch.index_select(env._obs_table, 0, nxt.view(-1), out=obs)
        following.get(keys.INSTANCE).update_(instance)
    for k, v in outs.items():
        torch.stack(v, 1, out=batch.get(k))
    return batch
