"""A family's batched env with one sub-environment, behind Gymnasium's API (the ``taskvar/`` ids).

:class:`FamilyGymEnv` steps the family's :class:`~taskvar_torch.envs.batched.BatchedFamilyEnv` with
``num_envs=1``, so its episodes are the batched env's sub-environment 0's, bit for bit; a family's
Gymnasium env is a subclass that supplies data and small hooks (docs/families.md). Seeding:
docs/reliability.md#gymnasium-seeding.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical

from taskvar_torch import keys, rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.batched import BatchedFamilyEnv


class FamilyGymEnv(gym.Env):
    """One sub-environment of a family's batched env as a Gymnasium env.

    ``render_mode``: ``None`` or one of ``metadata["render_modes"]``; ``**kwargs``: any of
    :attr:`arguments`, checked as the config's ``env.<family>`` keys, passed to :attr:`env_class`.
    Attributes: ``batched`` (the env it steps), ``horizon``, ``last_action`` (for renderers).
    """

    env_class: ClassVar[type[BatchedFamilyEnv]]
    """The family's batched env."""
    arguments: ClassVar[dict[str, Any]] = {}
    """The constructor's keyword arguments and their defaults (``env_class``'s names)."""
    family: ClassVar[str | None] = None
    """The family whose ``env.<family>`` config keys check the arguments (``None``: no check)."""
    reset_options: ClassVar[tuple[str, ...]] = ()
    """The keys ``reset(options=...)`` accepts (:meth:`check_options` reads them)."""
    observation_key: ClassVar[str] = keys.OBSERVATION
    """The batched env's key the Gymnasium observation is (a categorical one: ``Discrete``)."""
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, **kwargs: Any):
        unknown = sorted(set(kwargs) - set(self.arguments))
        if unknown:
            raise TypeError(
                f"{type(self).__name__} got unknown argument(s) {unknown}; it takes render_mode "
                f"and {sorted(self.arguments)}"
            )
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}"
            )
        args = {**self.arguments, **kwargs}
        if self.family is not None:
            gym_checks.check_as_config(
                self.family, self.config_section(args), args.get("instances")
            )
        self.batched = self.env_class(1, validate_actions=False, **args)  # step() checks actions
        self.render_mode = render_mode
        self.horizon = self.batched.horizon
        self.action_space = spaces.Discrete(int(self.batched.action_spec.space.n))
        self.observation_space = self.make_observation_space()
        self.last_action: int | None = None
        self._td: TensorDictBase | None = None  # sub-environment 0's data; None before a reset
        self._seeded = False

    # ---- what a family supplies beside the class attributes ----------------------------------

    def config_section(self, args: dict[str, Any]) -> dict[str, Any]:
        """The arguments as the config's ``env.<family>`` values (every one but ``instances``)."""
        return {k: v for k, v in args.items() if k != "instances"}

    def make_observation_space(self) -> spaces.Space:
        """``Discrete(n)`` for a categorical :attr:`observation_key`, else a float32 ``Box`` with
        the spec's bounds."""
        spec = self.batched.observation_spec[self.observation_key]
        if isinstance(spec, Categorical):
            return spaces.Discrete(int(spec.space.n))
        low, high = float(spec.space.low.min()), float(spec.space.high.max())
        return spaces.Box(low, high, (spec.shape[-1],), dtype=np.float32)

    def info(self, td: TensorDictBase) -> dict[str, Any]:
        """The ``info`` dict of sub-environment 0's data ``td`` (after a reset or a step)."""
        return {}

    def check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        """The checked reset ``options`` (keys from :attr:`reset_options`) as what :meth:`pin`
        installs; a one-line ``ValueError`` for a bad one. Nothing may change here."""
        return {}

    def pin(self, pins: dict[str, Any]) -> TensorDictBase:
        """Install :meth:`check_options`' result in the batched env's fresh episode (a pinned
        instance or start) and return sub-environment 0's data."""
        raise NotImplementedError(f"{type(self).__name__} takes no reset options")

    # ---- Gymnasium's API ---------------------------------------------------------------------

    def _observation(self, td: TensorDictBase) -> Any:
        obs = td.get(self.observation_key)[0]
        return int(obs) if isinstance(self.observation_space, spaces.Discrete) else obs.numpy()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start the next episode of this env's seed stream; ``options`` pin parts of it. Everything
        is checked before anything changes; ``seed`` is an integer in ``[0, 2**32 - 1]``.
        """
        pins = self.check_options(gym_checks.check_reset_options(options, self.reset_options))
        seed = None if seed is None else rng.check_seed(seed)
        super().reset(seed=seed)
        if seed is None and not self._seeded:  # first reset unseeded: Gymnasium's entropy
            seed = int(self.np_random.integers(0, rng.MAX_SEED + 1))
        if seed is not None:  # a seed restarts the stream at episode 0
            self.batched.set_seed(seed)
            self._seeded = True
        td = self.batched._reset(None)
        if pins:
            td = self.pin(pins)
        self._td, self.last_action = td, None
        return self._observation(td), self.info(td)

    def step(self, action: Any):
        """One step of the batched env; a one-line ``ValueError`` for an action out of range."""
        if self._td is None:
            raise RuntimeError("call reset() before step()")
        a = gym_checks.check_action(action, int(self.action_space.n))
        action = TensorDict._new_unsafe({keys.ACTION: torch.tensor([a])}, self.batched.batch_size)
        td = self.batched._step(action)
        self._td, self.last_action = td, a
        reward = float(td.get(keys.REWARD)[0, 0])
        terminated, truncated = bool(td.get(keys.TERMINATED)[0]), bool(td.get(keys.TRUNCATED)[0])
        return self._observation(td), reward, terminated, truncated, self.info(td)

    def render(self) -> str | np.ndarray | None:
        """Text (``ansi``) or a uint8 ``(H, W, 3)`` image (``rgb_array``) of the current state:
        the batched env's ``render(0, mode)``."""
        if self.render_mode is None:
            gym.logger.warn(
                "render() called with render_mode=None; pass render_mode to the constructor"
            )
            return None
        if self._td is None:
            raise RuntimeError("call reset() before render()")
        return self.batched.render(0, self.render_mode)
