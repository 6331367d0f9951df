"""MiniGrid's DoorKey as a task family, through taskvar_torch's Gymnasium adapter (docs/gymnasium.md).

Farama's ``minigrid`` package draws a new layout every episode (the wall's column, the door in
it, the key and the agent's start) from the reset seed, which the adapter draws from the
library's key: the layout is the hidden part of each instance, read back after each reset as
the door's and the key's cells. The grid's ``size`` is the instance's drawn parameter (a
constructor keyword argument: ``gym.make(id, size=...)``): 5 in training, 6 in the ``larger`` test. The agent sees its egocentric 7x7 view and its direction. Three options,
written as functions of the observation and the info that ``state_info`` reads from
``env.unwrapped``: get the key, open the door, reach the goal.
"""

from dataclasses import dataclass
from functools import partial

import minigrid  # noqa: F401  (registers the MiniGrid-* ids)
from minigrid.core.world_object import Door, Key

from taskvar_torch.families.gymnasium import Option, SpaceEncoder, gym_family


@dataclass(frozen=True)
class Size:
    """The grid's side, drawn uniformly from ``low..high`` (``--shift env.instances.high=6``)."""

    low: int = 5
    high: int = 5

    def __post_init__(self):
        if not 5 <= self.low <= self.high:
            raise ValueError(f"low and high must satisfy 5 <= low <= high, got {self}")

    def sample(self, rng):
        return {"size": int(rng.integers(self.low, self.high + 1))}


def cell_of(kind):
    """The flat cell of the first object of ``kind`` in the grid (-1: none, a carried key)."""
    return lambda env: next((i for i, x in enumerate(env.grid.grid) if isinstance(x, kind)), -1)


def state_info(env):
    """What the options read beyond the view: the key carried, the door open."""
    door = next(x for x in env.grid.grid if isinstance(x, Door))
    return {"has_key": isinstance(env.carrying, Key), "door_open": door.is_open}


OPTIONS = [
    Option(
        "get_key",
        initiation=lambda obs, info: not info["has_key"] and not info["door_open"],
        termination=lambda obs, info: info["has_key"] or info["door_open"],
        reward=lambda obs, info, r: float(info["has_key"]),
    ),
    Option(
        "open_door",
        initiation=lambda obs, info: info["has_key"] and not info["door_open"],
        termination=lambda obs, info: info["door_open"] or not info["has_key"],
        reward=lambda obs, info, r: float(info["door_open"]),
    ),
    Option("to_goal", initiation=lambda obs, info: info["door_open"]),  # the env's reward
]


def family():
    """The family (this package's ``taskvar_torch.families`` entry point)."""
    return gym_family(
        "doorkey",
        "MiniGrid-DoorKey-5x5-v0",
        instances={"train": Size(), "larger": Size(low=6, high=6)},
        options=OPTIONS,
        instance_via="kwargs",
        encoder=partial(SpaceEncoder, keys=("direction", "image")),  # not the mission's text
        state_info=state_info,
        instance_info={"door": cell_of(Door), "key": cell_of(Key)},  # the layout drawn
        horizon=100,
        description="MiniGrid DoorKey, the layout hidden (examples/minigrid_doorkey)",
    )
