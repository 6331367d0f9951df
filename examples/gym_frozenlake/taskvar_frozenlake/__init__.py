"""FrozenLake as a task family: Gymnasium's own env, its slipperiness hidden (docs/gymnasium.md).

Each episode draws FrozenLake's ``success_rate`` (the chance a move goes where it was meant to;
otherwise it slips to a side) from the instance distribution; it reaches the env as a constructor
keyword argument (``gym.make("FrozenLake-v1", success_rate=...)``). The agent sees its cell only.
Two options, written as functions of the observation: walk to the safe middle cell 10, and walk
to the goal, cell 15.
"""

from dataclasses import dataclass

from taskvar_torch.families.gymnasium import Option, gym_family

GOAL, MIDDLE = 15, 10


@dataclass(frozen=True)
class SuccessRate:
    """``success_rate ~ U[low, high]`` (``--shift env.instances.low=...``)."""

    low: float = 0.7
    high: float = 1.0

    def __post_init__(self):
        if not 0.0 <= self.low <= self.high <= 1.0:
            raise ValueError(f"low and high must satisfy 0 <= low <= high <= 1, got {self}")

    def sample(self, rng):
        return {"success_rate": float(rng.uniform(self.low, self.high))}


def waypoint(name, cell, reward=None):
    """Walk to ``cell``: startable elsewhere, ends there, rewarded 1 on arriving there."""
    return Option(
        name,
        initiation=lambda obs, info: int(obs) != cell,
        termination=lambda obs, info: int(obs) == cell,
        reward=reward or (lambda obs, info, r: float(int(obs) == cell)),
    )


def family():
    """The family (this package's ``taskvar_torch.families`` entry point)."""
    return gym_family(
        "frozenlake",
        "FrozenLake-v1",  # Gymnasium's id; an instance reaches it as make's keyword arguments
        instances={
            "train": SuccessRate(),
            "slippery": SuccessRate(low=0.3, high=0.6),
            "sure": SuccessRate(low=1.0, high=1.0),
        },
        options=[waypoint("middle", MIDDLE), waypoint("goal", GOAL, lambda obs, info, r: r)],
        instance_via="kwargs",
        description="FrozenLake 4x4, its success_rate hidden (examples/gym_frozenlake)",
    )
