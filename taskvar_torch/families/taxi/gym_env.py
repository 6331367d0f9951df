"""Taxi as a Gymnasium env (``taskvar/Taxi-v0``): one :class:`TaxiEnv` sub-environment behind
:class:`~taskvar_torch.envs.gym_env.FamilyGymEnv`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from taskvar_torch import keys, rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.gym_env import FamilyGymEnv
from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.env import _C_ARMED, TaxiEnv, check_state, instance_state

_INSTANCE_KEYS = ("is_rainy", "rainy_probability", "fickle_passenger", "fickle_probability")
_TAXI_V4_DEFAULTS = {"rainy_probability": 0.8, "fickle_probability": 0.3}


class TaxiGymEnv(FamilyGymEnv):
    """Taxi-v4 with a hidden rain / fickle-passenger instance per episode as one Gymnasium env.

    Observation ``Discrete(500)`` (Taxi-v4's state); actions, start, reward and episode end as
    :class:`TaxiEnv`; ``render_mode`` ``ansi`` or ``rgb_array``. ``reset(options={"instance": kw,
    "state": s})`` pins the instance with Taxi-v4's keyword names (``is_rainy``,
    ``rainy_probability``, ``fickle_passenger``, ``fickle_probability``; a missing key takes
    ``gym.make("Taxi-v4")``'s value) and the start state. ``info["instance"]`` reports the instance;
    ``info["action_mask"]`` is Taxi-v4's.
    """

    env_class = TaxiEnv
    family = "taxi"
    arguments = {"instances": "train", "horizon": 200}
    reset_options = ("instance", "state")
    observation_key = keys.CELL

    def info(self, td: TensorDictBase) -> dict[str, Any]:
        inst = td.get(keys.INSTANCE)
        q, f = float(inst["rainy_probability"][0]), float(inst["fickle_probability"][0])
        s = int(td.get(keys.CELL)[0])
        return {
            "instance": {
                "is_rainy": q < 1.0,
                "rainy_probability": q,
                "fickle_passenger": f > 0.0,
                "fickle_probability": f,
                "armed": bool(inst["armed"][0]),
            },
            "action_mask": (self.batched.model.next[s, :, 0] != s).numpy().astype(np.int8),
        }

    def check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        """``instance``: Taxi-v4's keywords (missing ones: Taxi-v4's defaults) as ``(q, f)``;
        ``state``: a Taxi-v4 state."""
        pins: dict[str, Any] = {}
        if options.get("instance") is not None:
            inst = gym_checks.check_fields(options["instance"], "instance", _INSTANCE_KEYS)
            for name in ("is_rainy", "fickle_passenger"):
                if not isinstance(inst.get(name, False), (bool, np.bool_)):
                    raise ValueError(f"instance {name} must be a bool, got {inst[name]!r}")
            probs = {
                name: gym_checks.check_probability(inst.get(name, default), f"instance {name}")
                for name, default in _TAXI_V4_DEFAULTS.items()
            }
            q = probs["rainy_probability"] if inst.get("is_rainy", False) else 1.0
            f = probs["fickle_probability"] if inst.get("fickle_passenger", False) else 0.0
            pins["instance"] = (q, f)
        if options.get("state") is not None:
            pins["state"] = check_state(options["state"], "state")
        return pins

    def pin(self, pins: dict[str, Any]) -> TensorDictBase:
        env, state = self.batched, {}
        if "instance" in pins:
            q, f = (torch.tensor([v], dtype=torch.float32) for v in pins["instance"])
            key = rng.episode_key(env._base_key, env._episode)  # this episode's, as at reset
            state.update(instance_state(q, f, rng.draw_bits(key, _C_ARMED)))
        if "state" in pins:
            state["_state"] = torch.tensor([pins["state"]])
        env.replace_state(state)
        return env._out()

    def render(self) -> str | np.ndarray | None:
        """As :class:`FamilyGymEnv`'s, with Taxi-v4's footer naming the last action (``ansi``)."""
        if self.render_mode != "ansi" or self._td is None:
            return super().render()
        inst = self._td.get(keys.INSTANCE)
        q, f = float(inst["rainy_probability"][0]), float(inst["fickle_probability"][0])
        return taxi.render_ansi(int(self._td.get(keys.CELL)[0]), q, f, self.last_action)
