"""The batched env of a Gymnasium family: ``N`` Gymnasium envs in a vector env (``autoreset_mode=
DISABLED``), behind the family contract (docs/families.md#the-env; docs/gymnasium.md). A trajectory
depends on ``(seed, index_offset + i, episode)`` and the user env's own randomness only; the family
is ``resumable=False``.
"""

from __future__ import annotations

import signal
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector.async_vector_env import AsyncState
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from taskvar_torch import keys
from taskvar_torch.envs.batched import BatchedFamilyEnv
from taskvar_torch.families.gymnasium.encoder import SpaceEncoder
from taskvar_torch.families.gymnasium.options import SUBTASK
from taskvar_torch.families.gymnasium.sub_env import INFO, SubEnv
from taskvar_torch.guest import UserCodeError, guest, short, user_error

VECTOR = ("sync", "async")
"""``env.NAME.vector``: Gymnasium's ``SyncVectorEnv`` (one process) or ``AsyncVectorEnv`` (one
process per sub-environment: worth it only where a step costs more than a process round trip)."""


def _shareable(space: gym.Space) -> bool:
    """Whether ``AsyncVectorEnv`` can pass observations of ``space`` through shared memory (not
    for a space of another package's, such as MiniGrid's ``MissionSpace``)."""
    basic = (gym.spaces.Box, gym.spaces.Discrete, gym.spaces.MultiDiscrete, gym.spaces.MultiBinary)

    def ok(space: gym.Space) -> bool:
        if isinstance(space, (gym.spaces.Dict, gym.spaces.Tuple)):
            subs = space.spaces.values() if isinstance(space, gym.spaces.Dict) else space.spaces
            return all(ok(s) for s in subs)
        return isinstance(space, basic)

    return ok(space)


class _AsyncVectorEnv(gym.vector.AsyncVectorEnv):
    """Gymnasium's ``AsyncVectorEnv``, whose worker errors that are a user's code's
    (:class:`~taskvar_torch.guest.UserCodeError`: already one line naming the family, the function
    and where) come back without Gymnasium's log of the worker's traceback."""

    def _raise_if_errors(self, successes) -> None:
        if all(successes):
            return
        errors = [self.error_queue.get() for _ in range(self.num_envs - sum(successes))]
        for index, *_ in errors:
            self.parent_pipes[index].close()
            self.parent_pipes[index] = None
        self._state = AsyncState.DEFAULT
        user = [e for e in errors if issubclass(e[1], UserCodeError)]
        if user:
            raise user[0][2]
        for index, _, _, trace in errors:  # as Gymnasium reports them
            gym.logger.error(f"Received the following error from Worker-{index}: {trace}")
        raise errors[-1][1](errors[-1][2])


def _sub_env(index: int, adapter: Any, first: dict, worker: bool) -> SubEnv:
    """Sub-environment ``index``; in a worker process (``vector=async``) Ctrl-C is ignored: the
    command's process handles it and closes the workers, and a ``KeyboardInterrupt`` raised there
    is the user's code's own (:func:`~taskvar_torch.guest.guest`)."""
    if worker:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return SubEnv(index, adapter, first)


class GymFamilyEnv(BatchedFamilyEnv):
    """``N`` sub-environments of a Gymnasium family (its :class:`~.family.GymAdapter`).

    Keys: ``observation`` (the adapter's encoder of the Gymnasium observation, float ``(N, D)``),
    ``("subtask", "initiation" | "termination" | "reward")`` (the options, ``(N, O)``),
    ``("instance", NAME)`` (each parameter of the hidden instance, drawn or read by
    ``instance_info``, float ``(N,)``).
    """

    runtime_state = ("_base_key", "_episode", "_t")
    """Saved by a checkpoint, but not enough to resume: the Gymnasium envs' state is not a tensor
    (the family declares ``resumable=False``)."""

    def __init__(
        self,
        adapter: Any,
        num_envs: int = 1,
        instances: Any = "train",
        seed: int = 0,
        index_offset: int = 0,
        noise_seed: int = 0,
        validate_actions: bool | None = None,
        vector: str = "sync",
        horizon: int = 0,
        device: torch.device | str = "cpu",
    ):
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        if vector not in VECTOR:
            raise ValueError(f"vector must be one of {list(VECTOR)}, got {vector!r}")
        self.adapter, self.vector = adapter, vector
        self.instances = adapter.instances.of(instances)
        self.index_offset, self.noise_seed = int(index_offset), int(noise_seed)
        if self.noise_seed != 0:
            raise ValueError(
                f"noise_seed must be 0 for a Gymnasium family, got {noise_seed}: the env draws its "
                "start and its per-step noise from one reset seed, so no seed keeps the one and "
                "changes the other"
            )
        self.validate_actions = (
            self.device.type == "cpu" if validate_actions is None else bool(validate_actions)
        )
        first = adapter.instances.draw(self.instances, 0)  # builds the envs; each reset redraws
        self.instance_keys = adapter.instance_keys  # drawn, then read (instance_info)
        fns = [self._sub_env_fn(i, first) for i in range(self.num_envs)]
        mode = gym.vector.AutoresetMode.DISABLED
        if vector == "sync":
            self.vec = gym.vector.SyncVectorEnv(fns, autoreset_mode=mode, copy=False)
        else:  # observations through shared memory where Gymnasium can share every part
            probe = SubEnv(0, adapter, first)
            probe.close()
            shared = _shareable(probe.observation_space)
            self.vec = _AsyncVectorEnv(fns, autoreset_mode=mode, shared_memory=shared, copy=False)
        space = self.vec.single_action_space
        if not isinstance(space, gym.spaces.Discrete):
            raise UserCodeError(
                f"family {adapter.name!r}: a Gymnasium family needs a Discrete action space, "
                f"the env's is {space}"
            )
        self.num_actions, self.action_start = int(space.n), int(space.start)  # start: mapped
        obs_space = self.vec.single_observation_space
        self.encoder = (
            adapter.encoder(obs_space)
            if adapter.encoder is SpaceEncoder
            else guest(adapter.name, "encoder(observation_space)", adapter.encoder, obs_space)
        )
        self.own_encoder = not isinstance(self.encoder, SpaceEncoder)  # the user's: a guest
        size = getattr(self.encoder, "size", None)
        if not isinstance(size, (int, np.integer)) or isinstance(size, bool) or size < 1:
            raise user_error(
                adapter.name,
                "encoder(observation_space)",
                f"returned an encoder whose size is {size!r}, not an int >= 1 (the observation's "
                "length)",
            )
        self.horizon = int(horizon) or adapter.horizon
        self.given = any(o.policy is not None for o in adapter.options)  # given-policy options
        self.robust = adapter.hierarchy is not None  # robustness rewards for its critics
        self._specs(int(self.encoder.size), len(adapter.options))
        self._set_seed(seed)

    def _sub_env_fn(self, i: int, first: dict):
        adapter, worker = self.adapter, self.vector == "async"
        return lambda: _sub_env(i, adapter, first, worker)

    def _specs(self, D: int, O: int) -> None:  # noqa: E741
        N, dev = self.num_envs, self.device
        low, high = getattr(self.encoder, "low", None), getattr(self.encoder, "high", None)
        obs = (
            Bounded(low.expand(N, D), high.expand(N, D), shape=(N, D), device=dev)
            if low is not None and bool(torch.isfinite(low).all() & torch.isfinite(high).all())
            else Unbounded(shape=(N, D), dtype=torch.float32, device=dev)
        )
        flag = Categorical(2, shape=(N, O), dtype=torch.bool, device=dev)
        subtask = Composite(
            initiation=flag,
            termination=flag.clone(),
            reward=Unbounded(shape=(N, O), dtype=torch.float32, device=dev),
            shape=(N,),
            device=dev,
        )
        if self.robust:  # the robustness rewards of a declared hierarchy's options
            subtask["robustness"] = Unbounded(shape=(N, O), dtype=torch.float32, device=dev)
        if self.given:  # each given policy's action index (-1: a learnt option)
            subtask["given_action"] = Bounded(
                -1, self.num_actions - 1, shape=(N, O), dtype=torch.int64, device=dev
            )
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: obs,
                SUBTASK: subtask,
                keys.INSTANCE: Composite(
                    {k: Unbounded(shape=(N,), device=dev) for k in self.instance_keys},
                    shape=(N,),
                    device=dev,
                ),
            },
            shape=(N,),
            device=dev,
        )
        self.action_spec = Categorical(self.num_actions, shape=(N,), dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(N, 1), dtype=torch.float32, device=dev)
        self.make_done_spec()

    def _options(
        self, info: dict, rows: np.ndarray | None
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """The options' evaluations in ``info`` (the vector env's ``(N, 3 O + H)``, see
        :meth:`SubEnv.report`), written over the current ones at ``rows`` (``None``: every row),
        and the ``(N, H)`` values ``instance_info`` read (meaningful after a reset)."""
        raw = torch.as_tensor(info[INFO]).to(device=self.device)
        x = raw.to(torch.float32)
        O = len(self.adapter.options)  # noqa: E741
        parts = {"_initiation": x[:, :O] > 0, "_termination": x[:, O : 2 * O] > 0}
        parts["_reward"] = x[:, 2 * O : 3 * O]
        if self.given:
            parts["_given"] = raw[:, 3 * O : 4 * O].to(torch.int64)
        if self.robust:
            parts["_robustness"] = x[:, 4 * O : 5 * O]
        if rows is not None:
            at = torch.as_tensor(rows, device=self.device)
            parts = {k: getattr(self, k).index_put((at,), v[at]) for k, v in parts.items()}
        return parts, x[:, 5 * O :]

    def _encode(self, obs, what: str, t: torch.Tensor | None = None) -> torch.Tensor:
        """The encoded batch in a tensor of its own, checked finite once per batch (``what``
        returned it, at steps ``t``; ``None``: a reset); a user encoder's output must be a finite
        ``(N, size)``.
        """
        name = self.adapter.name
        if self.own_encoder:
            x = guest(name, "encoder(obs)", self.encoder, obs)
            try:
                x = torch.as_tensor(x).clone()
            except (TypeError, ValueError, RuntimeError) as e:
                problem = f"returned {type(x).__name__}, not a tensor or array ({e})"
                raise user_error(name, "encoder(obs)", problem) from None
            shape = (self.num_envs, int(self.encoder.size))
            if tuple(x.shape) != shape:
                problem = f"returned shape {tuple(x.shape)}, not {shape} (N, encoder.size)"
                raise user_error(name, "encoder(obs)", problem)
            what = "encoder(obs)"
        else:
            x = self.encoder(obs)
        finite = torch.isfinite(x).all(dim=1)
        if not bool(finite.all()):
            i = int((~finite).nonzero()[0, 0])
            step = "reset" if t is None else f"step {int(t[i])}"
            problem = f"returned an observation with a non-finite value (nan or inf): {short(x[i].numpy())}"
            raise user_error(name, what, problem, f"sub-environment {i}, {step}")
        return x.to(device=self.device, dtype=torch.float32)

    def _out(self, reward=None, terminated=None, truncated=None) -> TensorDictBase:
        B = self.batch_size
        td = {
            keys.OBSERVATION: self._obs,
            SUBTASK: TensorDict._new_unsafe(
                {
                    "initiation": self._initiation,
                    "termination": self._termination,
                    "reward": self._reward,
                    **({"given_action": self._given} if self.given else {}),
                    **({"robustness": self._robustness} if self.robust else {}),
                },
                batch_size=B,
            ),
            keys.INSTANCE: TensorDict._new_unsafe(
                {k: self._instance[:, j] for j, k in enumerate(self.instance_keys)}, batch_size=B
            ),
        }
        return self.finish(td, reward, terminated, truncated)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        started = hasattr(self, "_obs")
        idx, key = self.next_episodes(tensordict, started)
        rows = np.arange(self.num_envs) if idx is None else idx.cpu().numpy()
        if not rows.size:
            return self._out()
        draw = self.adapter.instances.draw
        drawn = [draw(self.instances, k) for k in key.tolist()]
        instances: list[dict | None] = [None] * self.num_envs
        seeds: list[int | None] = [None] * self.num_envs
        for r, k, inst in zip(rows.tolist(), key.tolist(), drawn):
            instances[r] = inst
            seeds[r] = self.adapter.reset_seed(k)
        if idx is None:
            self._drawn, self._ended = instances, np.zeros(self.num_envs, dtype=bool)
        else:
            self._drawn = [d if i is None else i for d, i in zip(self._drawn, instances)]
            self._ended = self._ended & ~np.isin(np.arange(self.num_envs), rows)
        options: dict[str, Any] = {INFO: instances}
        if idx is not None:
            options["reset_mask"] = np.isin(np.arange(self.num_envs), rows)
        obs, info = self.vec.reset(seed=seeds, options=options)
        state, read = self._options(info, None if idx is None else rows)
        values = torch.tensor([[float(v) for v in d.values()] for d in drawn], dtype=torch.float32)
        values = values.reshape(len(drawn), -1).to(self.device)  # drawn, then read: (n, K + H)
        values = torch.cat([values, read if idx is None else read[idx]], dim=1)
        state["_obs"] = self._encode(obs, "env.reset(seed, options)")
        if idx is None:
            state["_instance"], state["_t"] = values, torch.zeros_like(key)
        else:
            state["_instance"] = self._instance.index_put((idx,), values)
            state["_t"] = self._t.index_put((idx,), torch.zeros_like(key))
        self.replace_state(state)
        return self._out()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION).reshape(-1)
        if self.validate_actions and bool(((action < 0) | (action >= self.num_actions)).any()):
            raise ValueError(
                f"action must be in [0, {self.num_actions - 1}], got {action.tolist()}"
            )
        if self._ended.any():  # stepped past its end (an evaluation's finished episodes): restart
            # it, with the same instance and no new episode key, so the vector env may step it
            self.vec.reset(options={"reset_mask": self._ended.copy(), INFO: self._drawn})
        obs, reward, terminated, truncated, info = self.vec.step(
            action.cpu().numpy() + self.action_start
        )
        t = self._t + 1
        state, _ = self._options(info, None)
        state["_obs"], state["_t"] = self._encode(obs, "env.step(action)", t), t
        self.replace_state(state)
        dev = self.device
        term = torch.as_tensor(terminated, device=dev).reshape(-1, 1)
        trunc = torch.as_tensor(truncated, device=dev).reshape(-1, 1) | (t >= self.horizon)[:, None]
        r = torch.as_tensor(reward, dtype=torch.float32, device=dev).reshape(-1, 1)
        self._ended = (term | trunc).reshape(-1).cpu().numpy()
        return self._out(r, term, trunc & ~term)

    def state_bounds(self) -> dict[str, tuple[float, float]]:
        return {**super().state_bounds(), "t": (0, self.horizon)}

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the vector env (its worker processes with ``vector=async``)."""
        if not getattr(self, "is_closed", True) and hasattr(self, "vec"):
            self.vec.close()
        super().close(raise_if_closed=raise_if_closed)


__all__ = ["VECTOR", "GymFamilyEnv"]
