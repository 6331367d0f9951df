"""Wargus as a Gymnasium env (``taskvar/Wargus-v0``, ``taskvar/Wargus-Large-v0``; paper §3.5):
one :class:`WargusEnv` sub-environment behind :class:`~taskvar_torch.envs.gym_env.FamilyGymEnv`."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDictBase

from taskvar_torch import keys, rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.gym_env import FamilyGymEnv
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus import render as wargus_render
from taskvar_torch.families.wargus.dynamics import WargusConfig
from taskvar_torch.families.wargus.env import WargusEnv


class WargusGymEnv(FamilyGymEnv):
    """Wargus (paper §3.5) as one Gymnasium env over :class:`WargusEnv` (docs/gymnasium.md):
    ``Discrete(8)`` (9 with ``noop``), ``Box(24,)``; arguments the :class:`WargusConfig` fields,
    ``instances``, ``render_mode``; ``reset(options={"instance": {"seed": s}, "start": (row,
    col)})`` pins an episode; ``info`` holds the instance, the subtasks' integer state and ``t``.
    """

    env_class = WargusEnv
    family = "wargus"
    arguments = {
        "size": 32,
        "num_patrols": 1,
        "num_items": 1,
        "sight": 8,
        "shoot_range": 5,
        "hit_prob": 1.0,
        "patrol_speed": 0.8,
        "horizon": 500,
        "noop": False,
        "instances": "train",
    }
    reset_options = ("instance", "start")
    metadata = {"render_modes": list(wargus_render.RENDER_MODES), "render_fps": 8}

    @property
    def config(self) -> WargusConfig:
        return self.batched.config

    def make_observation_space(self) -> spaces.Box:
        """The observation's per-element bounds (``WargusModel.obs_low``, ``obs_high``)."""
        m = self.batched.model
        low, high = m.obs_low.numpy(), m.obs_high.numpy()
        return spaces.Box(low=low, high=high, shape=(wargus.OBS_DIM,), dtype=np.float32)

    def info(self, td: TensorDictBase) -> dict[str, Any]:
        inst = td.get(keys.INSTANCE)
        return {
            "instance": {
                "seed": int(inst[wargus.INSTANCE_SEED][0]),
                "patrol_pos": inst[wargus.PATROL_POS][0].numpy().copy(),
                "item_pos": inst[wargus.ITEM_POS][0].numpy().copy(),
            },
            wargus.AGENT_POS: tuple(int(v) for v in td.get(wargus.AGENT_POS)[0]),
            wargus.ITEM_SEEN: bool(td.get(wargus.ITEM_SEEN)[0]),
            wargus.PATROL_SEEN: bool(td.get(wargus.PATROL_SEEN)[0]),
            wargus.PICKED: int(td.get(wargus.PICKED)[0]),
            wargus.ITEM_LOST: bool(td.get(wargus.ITEM_LOST)[0]),
            "t": int(self.batched._state.t[0]),
        }

    def check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        """``instance``: ``{"seed": s}``, an instance seed in ``[0, 2^32)``; ``start``: a cell."""
        pins: dict[str, Any] = {}
        if options.get("instance") is not None:
            inst = gym_checks.check_fields(options["instance"], "instance", ("seed",))
            s = gym_checks.as_int(inst.get("seed"))
            if s is None or not 0 <= s <= rng.MASK32:
                raise ValueError(
                    f"instance seed must be an integer in [0, {rng.MASK32}], got {inst.get('seed')!r}"
                )
            pins["seed"] = s
        if options.get("start") is not None:
            size = self.config.size
            pins["start"] = gym_checks.check_cell(options["start"], size, size)
        return pins

    def pin(self, pins: dict[str, Any]) -> TensorDictBase:
        """The episode again from the pinned instance seed and start cell (``wargus.reset``)."""
        env = self.batched
        iseed = torch.tensor([pins["seed"]]) if "seed" in pins else env._iseed
        ikey = wargus.instance_key(iseed)
        start = torch.tensor(pins["start"]) if "start" in pins else None
        env.replace_state(
            {"_iseed": iseed, "_ikey": ikey, "_state": wargus.reset(env.model, ikey, start)}
        )
        return env._out(env._picked, env._item_lost)
