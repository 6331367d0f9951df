"""The windy gridworld as a Gymnasium env (``taskvar/WindyGrid-v0`` and its layouts): one
:class:`WindyGridEnv` sub-environment behind :class:`~taskvar_torch.envs.gym_env.FamilyGymEnv`."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys, rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.gym_env import FamilyGymEnv
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.env import WindyGridEnv, start_cell


class WindyGridGymEnv(FamilyGymEnv):
    """The windy family (paper §3.3.1) as one Gymnasium env over :class:`WindyGridEnv`
    (docs/gymnasium.md): ``Discrete(4)``, ``Box(0, 1, (D,))``; ``reset(options={"instance": {"p",
    "direction"}, "start": (row, col)})`` pins an episode; ``info`` has ``instance`` and ``cell``.
    """

    env_class = WindyGridEnv
    family = "windy"
    arguments = {
        "layout": "default",
        "instances": "train",
        "horizon": None,
        "obs_encoding": "onehot",
        "patch_radius": 2,
    }
    reset_options = ("instance", "start")

    @property
    def layout(self) -> windy.WindyLayout:
        return self.batched.layout

    def config_section(self, args: dict[str, Any]) -> dict[str, Any]:
        section = super().config_section(args)
        if isinstance(section["layout"], windy.WindyLayout):  # the config holds a map string
            section["layout"] = "\n".join(section["layout"].rows)
        return section

    def info(self, td: TensorDictBase) -> dict[str, Any]:
        direction = windy.DIRECTIONS[int(td.get((keys.INSTANCE, "direction"))[0])]
        return {
            "instance": {"p": float(td.get((keys.INSTANCE, "p"))[0]), "direction": direction},
            "cell": divmod(int(td.get(keys.CELL)[0]), self.layout.width),
        }

    def check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        pins: dict[str, Any] = {}
        if options.get("instance") is not None:
            inst = gym_checks.check_fields(options["instance"], "instance", ("p", "direction"))
            if "p" in inst:
                pins["_p"] = gym_checks.check_probability(inst["p"], "instance p")
            if "direction" in inst:
                pins["_dir"] = windy.direction_index(inst["direction"])
        if options.get("start") is not None:
            pins["_cell"] = start_cell(self.layout, options["start"])
        return pins

    def pin(self, pins: dict[str, Any]) -> TensorDictBase:
        env = self.batched
        state = {k: torch.tensor([v], dtype=getattr(env, k).dtype) for k, v in pins.items()}
        if "_p" in state:  # the gust threshold follows p
            state["_threshold"] = rng.probability_threshold(state["_p"])
        env.replace_state(state)
        return env._out(env._cell, env._p, env._dir)
