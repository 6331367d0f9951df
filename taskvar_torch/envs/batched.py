"""What every batched family env shares: specs, seeding and reset around pure dynamics
(docs/families.md#the-env).

A family env implements TorchRL's ``_reset`` and ``_step`` and calls
:meth:`~BatchedFamilyEnv.make_done_spec`, :meth:`~BatchedFamilyEnv.next_episodes`,
:meth:`~BatchedFamilyEnv.replace_state` and :meth:`~BatchedFamilyEnv.finish`, and lists in
:attr:`~BatchedFamilyEnv.runtime_state` what a checkpoint saves. State tensors are replaced, never
mutated, and ``_reset`` returns every sub-environment's data, so a partial reset is a plain update.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite
from torchrl.envs import EnvBase

from taskvar_torch import keys, rng


def _deprecated(old: str, new: str) -> None:
    warnings.warn(
        f"BatchedFamilyEnv.{old} is deprecated; use {new} (docs/families.md)",
        FutureWarning,
        stacklevel=3,
    )


class BatchedFamilyEnv(EnvBase):
    """Base of every family's batched env: done specs, keyed seeding, episode counters, partial
    resets and exact resume (``env.state_dict()``)."""

    batch_locked = True
    runtime_state: tuple[str, ...] = ("_base_key", "_episode")
    """Names of the tensor attributes ``(N, ...)`` that change as the env runs: what
    ``env.state_dict()`` saves so that a loaded env continues every episode exactly (a training
    checkpoint's ``env`` entry). List every one your ``_reset`` and ``_step`` write (with
    :meth:`replace_state`) and read back, the base's ``_base_key`` and ``_episode`` included;
    :func:`~taskvar_torch.check_family` names one left out. Each is saved under its name without
    the leading underscore."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "_RUNTIME_STATE" in cls.__dict__:  # the deprecated spelling
            warnings.warn(
                f"{cls.__name__}._RUNTIME_STATE is deprecated; name it runtime_state "
                "(docs/families.md)",
                FutureWarning,
                stacklevel=2,
            )
            cls.runtime_state = tuple(cls.__dict__["_RUNTIME_STATE"])

    @property
    def num_envs(self) -> int:
        return self.batch_size[0]

    def make_done_spec(self) -> None:
        """Set the ``done``, ``terminated`` and ``truncated`` specs, each ``(N, 1)`` bool; call it
        in the constructor beside the observation, action and reward specs."""
        N, dev = self.num_envs, self.device
        flag = Categorical(2, shape=(N, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(
            {k: flag.clone() for k in (keys.DONE, keys.TERMINATED, keys.TRUNCATED)},
            shape=(N,),
            device=dev,
        )

    def _set_seed(self, seed: int | None) -> None:
        """Sub-environment ``i`` draws from key ``(seed, index_offset + i)``: any split of N agrees.

        TorchRL's hook (``env.set_seed``); the constructor calls it with its ``seed``.
        """
        seed = 0 if seed is None else int(seed)
        index = torch.arange(self.num_envs, device=self.device) + self.index_offset
        self._base_key = rng.sub_env_key(seed, index)  # (N,)
        self._episode = torch.full((self.num_envs,), -1, dtype=torch.int64, device=self.device)
        self._seed = seed

    def set_seed_blocks(self, seeds: Sequence[int]) -> None:
        """Split the ``N`` sub-environments into ``S = len(seeds)`` equal blocks, block ``s``
        drawing exactly what an env of ``N / S`` sub-environments seeded ``seeds[s]`` draws:
        sub-env ``s N / S + i`` keys from ``(seeds[s], index_offset + i)`` (``taskvar train
        --seeds``: one batched env for every run). Call it before the first reset."""
        S = len(seeds)
        if S < 1 or self.num_envs % S:
            raise ValueError(f"{self.num_envs} sub-environments do not split into {S} seeds")
        n = self.num_envs // S
        index = torch.arange(n, device=self.device) + self.index_offset
        self._base_key = torch.cat([rng.sub_env_key(int(sd), index) for sd in seeds])
        self._episode = torch.full((self.num_envs,), -1, dtype=torch.int64, device=self.device)

    def next_episodes(
        self, tensordict: TensorDictBase | None, started: bool
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        """Start the next episode of the sub-envs ``_reset`` resets; returns ``(indices or None,
        keys)``.

        Call it first in ``_reset(tensordict)`` (``started``: the env has state yet). It advances
        the episode counter of the sub-envs the ``"_reset"`` mask names (all where there is none)
        and returns their indices ``(n,)`` and episode keys ``(n,)``: draw the new episodes from
        these keys only.
        """
        reset = None if tensordict is None else tensordict.get("_reset", None)
        return self.next_episodes_where(reset if started else None)

    def next_episodes_where(
        self, reset: torch.Tensor | None
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        """:meth:`next_episodes` from the reset mask itself (``(N,)`` or ``(N, 1)`` bool;
        ``None``: every sub-environment)."""
        if reset is None:
            self.replace_state({"_episode": self._episode + 1})
            return None, rng.episode_key(self._base_key, self._episode)
        idx = reset.reshape(-1).nonzero().squeeze(-1)  # (n,) sub-envs to reset
        episode = self._episode.index_select(0, idx).add_(1)
        self.replace_state({"_episode": self._episode.index_put((idx,), episode)})
        return idx, rng.episode_key(self._base_key.index_select(0, idx), episode)

    def replace_state(self, state: dict[str, torch.Tensor]) -> None:
        """Replace simulator state tensors by name (plain attributes, bypassing ``nn.Module``'s
        checks); replace a tensor rather than mutate it, as handed-out tensordicts hold it.
        """
        self.__dict__.update(state)

    def get_runtime_state(self) -> dict[str, torch.Tensor]:
        """The :attr:`runtime_state` tensors, keyed by name without the leading underscore.

        Override it (with :meth:`set_runtime_state`) only for state that is not a plain tensor
        attribute (Wargus flattens its ``WargusState`` tuple)."""
        return {name[1:]: getattr(self, name) for name in self.runtime_state if hasattr(self, name)}

    def set_runtime_state(self, state: dict[str, torch.Tensor]) -> None:
        """Install what :meth:`get_runtime_state` returned (checked by :meth:`set_extra_state`)."""
        for name in self.runtime_state:
            if name[1:] in state:
                setattr(self, name, state[name[1:]])

    def get_extra_state(self) -> dict:
        """Runtime state for exact resume (the seed and :meth:`get_runtime_state`), so
        ``env.load_state_dict(other.state_dict())`` continues ``other``'s episodes exactly.
        """
        state = {k: v.clone() for k, v in self.get_runtime_state().items()}
        state["seed"] = self._seed
        return state

    def state_bounds(self) -> dict[str, tuple[float, float]]:
        """Inclusive ``(low, high)`` of the runtime-state entries whose values index tables or
        the grid (cells, directions, positions, step counters, probabilities): a saved state
        outside them is refused by :meth:`set_extra_state` instead of indexing out of range."""
        return {"episode": (0, 2**62)}

    def set_extra_state(self, state: dict) -> None:
        """Restore :meth:`get_extra_state` (the env must have the same ``num_envs``; every entry
        of :meth:`state_bounds` within its range, else a one-line ``ValueError``)."""
        tensors = {}
        bounds = self.state_bounds()
        for k, v in state.items():
            if k == "seed":
                continue
            value = torch.as_tensor(v, device=self.device)
            if value.shape[:1] != (self.num_envs,):
                raise ValueError(
                    f"env state {k!r} has shape {tuple(value.shape)}, expected ({self.num_envs}, ...): "
                    "num_envs must match the saved env"
                )
            if k in bounds and value.numel():
                low, high = bounds[k]
                v64 = value.to(torch.float64)
                if not (bool(torch.isfinite(v64).all()) and low <= v64.min() and v64.max() <= high):
                    bad = v64[~(torch.isfinite(v64) & (v64 >= low) & (v64 <= high))][0].item()
                    raise ValueError(f"env state {k!r} holds {bad:g}, outside [{low:g}, {high:g}]")
            tensors[k] = value.clone()
        self.set_runtime_state(tensors)
        self._seed = rng.check_seed(state["seed"], "env state 'seed'")

    def finish(
        self,
        td: dict,
        reward: torch.Tensor | None = None,  # (N, 1) float32
        terminated: torch.Tensor | None = None,  # (N, 1) bool
        truncated: torch.Tensor | None = None,  # (N, 1) bool
    ) -> TensorDictBase:
        """The tensordict ``_reset`` or ``_step`` returns: ``td`` (a plain dict of every
        sub-environment's observation keys) with the reward (after a step) and the done flags
        (all False after a reset; ``done = terminated | truncated``)."""
        if terminated is None:
            terminated = torch.zeros(self.num_envs, 1, dtype=torch.bool, device=self.device)
            truncated = terminated
        else:
            td[keys.REWARD] = reward
        td[keys.TERMINATED] = terminated
        td[keys.TRUNCATED] = truncated
        td[keys.DONE] = terminated | truncated
        return TensorDict._new_unsafe(td, batch_size=self.batch_size, device=self.device)

    # The deprecated spellings, for families written against them.
    def _make_done_spec(self) -> None:
        _deprecated("_make_done_spec", "make_done_spec")
        self.make_done_spec()

    def _next_episodes(self, tensordict, started):
        _deprecated("_next_episodes", "next_episodes")
        return self.next_episodes(tensordict, started)

    def _set_state(self, state: dict[str, torch.Tensor]) -> None:
        _deprecated("_set_state", "replace_state")
        self.replace_state(state)

    def _finish(self, td, reward=None, terminated=None, truncated=None) -> TensorDictBase:
        _deprecated("_finish", "finish")
        return self.finish(td, reward, terminated, truncated)

    def _reset_proc_data(self, tensordict, tensordict_reset):
        # ``_reset`` returns every sub-environment's current data, so a plain update is exact.
        self._complete_done(self.full_done_spec, tensordict_reset)
        if tensordict is None:
            return tensordict_reset
        tensordict.pop("_reset", None)
        return tensordict.update(tensordict_reset)
