"""One MiniGrid env of the port behind Gymnasium's API (``taskvar/MiniGrid-DoorKey-5x5-v0``, ...);
``info`` holds MiniGrid's own ``image`` and ``direction``.
"""

from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase

from taskvar_torch.envs.gym_env import FamilyGymEnv
from taskvar_torch.families.minigrid.env import MiniGridEnv


class MiniGridGymEnv(FamilyGymEnv):
    """MiniGrid DoorKey or LavaGap (the port) as a Gymnasium env: ``task``, ``size``, ``max_steps``,
    ``obs_encoding`` as :class:`MiniGridEnv`; ``instances`` default ``minigrid``; ``render_mode``
    ``ansi`` or ``rgb_array``.
    """

    env_class = MiniGridEnv
    family = "minigrid"
    arguments = {
        "task": "doorkey",
        "size": 5,
        "max_steps": None,
        "obs_encoding": "onehot",
        "instances": "minigrid",
    }
    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 10}

    def config_section(self, args: dict[str, Any]) -> dict[str, Any]:
        section = super().config_section(args)
        section["max_steps"] = section["max_steps"] or 0  # the config's 0: MiniGrid's own
        return section

    def info(self, td: TensorDictBase) -> dict[str, Any]:
        return {"image": self.batched.image()[0].numpy(), "direction": int(self.batched._dir[0])}
