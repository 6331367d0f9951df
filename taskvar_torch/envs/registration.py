"""Gymnasium registration under the ``taskvar/`` namespace (done on ``import taskvar_torch``)."""

from __future__ import annotations

import gymnasium as gym

from taskvar_torch.envs.windy import make_layout

_WINDY = "taskvar_torch.envs.windy_gym:WindyGridGymEnv"
_WARGUS = "taskvar_torch.envs.wargus_gym:WargusGymEnv"
_TAXI = "taskvar_torch.envs.taxi_gym:TaxiGymEnv"


def _map(layout) -> str:
    return "\n".join(layout.rows)


ENV_IDS: dict[str, tuple[str, dict]] = {
    "taskvar/WindyGrid-v0": (_WINDY, {"layout": "default"}),
    "taskvar/WindyGrid-MiddleExits-v0": (_WINDY, {"layout": "middle_exits"}),
    "taskvar/WindyGrid-WholeColumnWindy-v0": (_WINDY, {"layout": "whole_column_windy"}),
    "taskvar/WindyGrid-25x25-v0": (
        _WINDY,
        {"layout": _map(make_layout(25, 25, num_exits=2)), "obs_encoding": "coords_patch"},
    ),
    "taskvar/WindyGrid-51x51-4Exits-v0": (
        _WINDY,
        {"layout": _map(make_layout(51, 51, num_exits=4)), "obs_encoding": "coords_patch"},
    ),
    "taskvar/Wargus-v0": (_WARGUS, {}),
    "taskvar/Wargus-Large-v0": (_WARGUS, {"size": 64, "num_patrols": 3, "horizon": 1000}),
    "taskvar/Taxi-v0": (_TAXI, {}),
}


def register_envs() -> None:
    """Register every ``taskvar/`` id (idempotent)."""
    for env_id, (entry_point, kwargs) in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(
                id=env_id, entry_point=entry_point, kwargs=kwargs, disable_env_checker=False
            )
