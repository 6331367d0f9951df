"""Gymnasium ``Env`` for one Taxi (``taskvar/Taxi-v0``): Taxi-v4 with a hidden, per-episode
instance of rain and fickle passenger.

It steps the same lookup tables (``taxi.py``) and keyed random stream as :class:`TaxiEnv`, so with
the same seed it produces bit-identical trajectories to sub-environment 0 of the TorchRL env. To
register it (``registration.py``)::

    "taskvar/Taxi-v0": ("taskvar_torch.families.taxi.gym_env:TaxiGymEnv", {}),
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from taskvar_torch import rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.gym_episodes import EpisodeKeys
from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.dynamics import TaxiInstances, taxi_instances
from taskvar_torch.families.taxi.env import _C_ARMED, _C_START, check_state

_OPTION_KEYS = ("instance", "state")
_INSTANCE_KEYS = ("is_rainy", "rainy_probability", "fickle_passenger", "fickle_probability")
_TAXI_V4_DEFAULTS = {"rainy_probability": 0.8, "fickle_probability": 0.3}


def _thresholds(q: float, f: float) -> tuple[int, int, int]:
    """The env's integer thresholds for ``q`` and ``f`` (float32 values, as TaxiEnv stores them):
    intended move, left lateral, arming."""
    q64 = torch.tensor([q], dtype=torch.float32).to(torch.float64)
    fq = torch.tensor([f], dtype=torch.float32)
    return (
        int(rng.probability_threshold(q64)[0]),
        int(rng.probability_threshold(0.5 * (1.0 + q64))[0]),
        int(rng.probability_threshold(fq)[0]),
    )


class TaxiGymEnv(gym.Env):
    """Taxi-v4 with a hidden rain / fickle-passenger instance per episode, as a Gymnasium env.

    ## Description
    Dietterich's Taxi on Taxi-v4's map and rules (exactly: ``tests/families/taxi/test_taxi_env.py`` checks the
    dynamics against Gymnasium's). At every reset an instance is drawn from ``instances``: how
    likely a move slips sideways in the rain, and how likely the passenger changes destination on
    the first move after pickup. The agent does not observe it.

    ## Action Space
    ``Discrete(6)``: 0 south, 1 north, 2 east, 3 west, 4 pickup, 5 dropoff.

    ## Observation Space
    ``Discrete(500)``: Taxi-v4's state ``((row * 5 + col) * 5 + passenger) * 4 + destination``.

    ## Starting State
    Uniform over Taxi-v4's 300 initial states, or ``options={"state": s}``.

    ## Reward
    -1 per step, +20 for a delivery, -10 for an illegal pickup or dropoff.

    ## Episode End
    ``terminated`` on delivery, ``truncated`` after ``horizon`` steps (200, Taxi-v4's limit).

    ## Arguments
    ``instances`` (:attr:`TaxiInstances.NAMES`, a dict of fields or a :class:`TaxiInstances`),
    ``horizon``, ``render_mode`` (``ansi`` or ``rgb_array``).

    ## Task parameters
    ``reset(options={"instance": {"is_rainy": True, "rainy_probability": 0.7,
    "fickle_passenger": True, "fickle_probability": 0.3}})`` pins an instance with Taxi-v4's
    keyword names and defaults (a missing key takes ``gym.make("Taxi-v4")``'s value), so
    ``options={"instance": kw}`` behaves like ``gym.make("Taxi-v4", **kw)``. ``info["instance"]``
    reports the instance (``rainy_probability`` 1.0 when dry, ``fickle_probability`` 0.0 when not
    fickle); ``info["action_mask"]`` is Taxi-v4's.

    Examples:
        >>> env = TaxiGymEnv(render_mode="ansi")
        >>> obs, info = env.reset(seed=0, options={"instance": {"is_rainy": True}})
        >>> info["instance"]["rainy_probability"], env.observation_space.contains(obs)
        (0.800000011920929, True)
    """

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}

    def __init__(
        self,
        instances: str | TaxiInstances | dict = "train",
        horizon: int = 200,
        render_mode: str | None = None,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}"
            )
        gym_checks.check_as_config("taxi", {"horizon": horizon}, instances)
        self.instances = taxi_instances(instances)
        self.horizon = int(horizon)
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.render_mode = render_mode
        self.model = taxi.TaxiModel("cpu")
        self.observation_space = gym.spaces.Discrete(taxi.NUM_STATES)
        self.action_space = gym.spaces.Discrete(taxi.NUM_ACTIONS)
        self._next = self.model.np_next.tolist()
        self._reward = self.model.np_reward.astype(float).tolist()
        self._done = self.model.np_done.tolist()
        self._targets = self.model.np_fickle_targets.tolist()
        self._keys = EpisodeKeys()  # seeded at the first reset
        self._state, self._t, self._key, self._last_action = 0, 0, 0, None
        self._q, self._f, self._armed = np.float32(1.0), np.float32(0.0), False
        self._thr = (1 << 24, 1 << 24, 0)
        self._started = False  # step() before the first reset() is an error

    def _info(self) -> dict[str, Any]:
        q, f = float(self._q), float(self._f)
        mask = (self.model.np_next[self._state, :, 0] != self._state).astype(np.int8)
        return {
            "instance": {
                "is_rainy": q < 1.0,
                "rainy_probability": q,
                "fickle_passenger": f > 0.0,
                "fickle_probability": f,
                "armed": self._armed,
            },
            "action_mask": mask,
        }

    def _pinned(self, instance: Any) -> tuple[np.float32, np.float32]:
        """``(q, f)`` of a Taxi-v4-style keyword dict (missing keys: Taxi-v4's defaults)."""
        inst = gym_checks.check_fields(instance, "instance", _INSTANCE_KEYS)
        for name in ("is_rainy", "fickle_passenger"):
            if not isinstance(inst.get(name, False), (bool, np.bool_)):
                raise ValueError(f"instance {name} must be a bool, got {inst[name]!r}")
        probs = {}
        for name, default in _TAXI_V4_DEFAULTS.items():
            probs[name] = gym_checks.check_probability(inst.get(name, default), f"instance {name}")
        q = probs["rainy_probability"] if inst.get("is_rainy", False) else 1.0
        f = probs["fickle_probability"] if inst.get("fickle_passenger", False) else 0.0
        return np.float32(q), np.float32(f)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``options`` may hold ``instance`` (Taxi-v4 keywords) and ``state``.

        Every option is checked before anything changes: a refused reset leaves the env as it was.

        ``seed`` is an integer in ``[0, 2**32 - 1]`` (the keyed streams' 32-bit keys; a larger one
        is a ``ValueError``, never wrapped). Without ``seed`` the first reset draws one from
        Gymnasium's ``np_random`` (entropy), later ones continue that stream, as Gymnasium's own
        envs do: two unseeded envs, or ``gym.make_vec`` sub-envs, play different episodes.
        """
        options = gym_checks.check_reset_options(options, _OPTION_KEYS)
        pinned = None
        if options.get("instance") is not None:
            pinned = self._pinned(options["instance"])
        state = None
        if options.get("state") is not None:
            state = check_state(options["state"], "state")
        seed = None if seed is None else rng.check_seed(seed)
        super().reset(seed=seed)
        key = self._keys.next(seed, self.np_random)  # (1,)
        q, f = self.instances.sample(key)
        self._q, self._f = (np.float32(q[0].item()), np.float32(f[0].item()))
        if pinned is not None:
            self._q, self._f = pinned
        self._key = int(key[0])  # python-int hashing is the fastest for a single env
        starts = self.model.np_start_states
        self._state = int(starts[rng.index_of(rng.draw_bits(self._key, _C_START), len(starts))])
        if state is not None:
            self._state = state
        self._thr = _thresholds(float(self._q), float(self._f))
        self._armed = (rng.draw_bits(self._key, _C_ARMED) >> 8) < self._thr[2]
        self._t, self._last_action = 0, None
        self._started = True
        return self._state, self._info()

    def step(self, action):
        """Move (slipping sideways in the rain), pick up or drop off; Taxi-v4's rewards."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        a = gym_checks.check_action(action, taxi.NUM_ACTIONS)
        s = self._state
        u = rng.draw_bits(self._key, 2 * self._t) >> 8
        outcome = (u >= self._thr[0]) + (u >= self._thr[1])
        nxt = self._next[s][a][outcome]
        if self._armed and (s // 4) % 5 == taxi.IN_TAXI and s // 20 != nxt // 20:
            redraw = rng.index_of(rng.draw_bits(self._key, 2 * self._t + 1), 3)
            nxt, self._armed = self._targets[nxt][redraw], False
        self._state, self._last_action = nxt, a
        self._t += 1
        terminated = self._done[s][a]
        truncated = self._t >= self.horizon and not terminated
        return nxt, self._reward[s][a], terminated, truncated, self._info()

    def render(self):
        if self.render_mode == "ansi":
            return taxi.render_ansi(self._state, float(self._q), float(self._f), self._last_action)
        if self.render_mode == "rgb_array":
            return taxi.render_rgb(self._state)
        return None
