"""MiniGrid options (paper §3.2, §3.4.2): DoorKey's get key -> open door -> to goal, LavaGap's to
gap -> to goal, each under the full task (docs/minigrid.md#options-and-the-hierarchy).

Computed from the integer state the env writes (``cell``, ``carrying``, ``door``, ``side``) at
``td`` (s) and ``("next", ...)`` (s'), plus ``("next", "reward")``; outputs ``(*B, O)`` in ``names``
order. Each component is initiable where its subgoal is next (exactly one in every state), ends
outside its initiation set or at the goal, and earns +1 on its subgoal; the full task (``doorkey``,
``lavagap``) earns the env reward and never ends. Robustness rewards (§3.4.3): +1 on reaching the
subgoal, -1 on undoing it or dying on lava; the root the sum.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.families.minigrid.dynamics import OBJECT_TO_IDX, STATE_TO_IDX
from taskvar_torch.families.minigrid.env import CARRYING, DOOR, SIDE
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

KEY, OPEN, LOCKED = OBJECT_TO_IDX["key"], STATE_TO_IDX["open"], STATE_TO_IDX["locked"]
LEFT, GAP, RIGHT, LAVA = range(4)


def _at_goal(td: TensorDictBase, size: int) -> torch.Tensor:
    pos = td.get(keys.CELL) // 4
    return pos == (size - 2) * size + (size - 2)


class DoorKeySubtasks(Subtasks):
    """get key, open door, to goal and the full task (module docstring)."""

    names = ("get_key", "open_door", "to_goal", "doorkey")
    hierarchy = Hierarchy(root="doorkey", children={"doorkey": ("get_key", "open_door", "to_goal")})

    def __init__(self, size: int):
        self.size = int(size)

    def initiation(self, td: TensorDictBase) -> torch.Tensor:
        door, key = td.get(DOOR), td.get(CARRYING) == KEY
        get_key = (door == LOCKED) & ~key
        open_door = (door != OPEN) & (key | (door != LOCKED))
        return torch.stack([get_key, open_door, door == OPEN, torch.ones_like(key)], -1)

    def termination(self, td: TensorDictBase) -> torch.Tensor:
        end = _at_goal(td, self.size).unsqueeze(-1)
        beta = ~self.initiation(td) | end
        beta[..., -1] = False
        return beta

    def _events(self, td: TensorDictBase) -> tuple[torch.Tensor, ...]:
        nxt = td.get(keys.NEXT)
        key, key2 = td.get(CARRYING) == KEY, nxt.get(CARRYING) == KEY
        door, door2 = td.get(DOOR) == OPEN, nxt.get(DOOR) == OPEN
        goal = _at_goal(nxt, self.size)
        return key2 & ~key, key & ~key2, door2 & ~door, door & ~door2, goal

    def reward(self, td: TensorDictBase) -> torch.Tensor:
        picked, _, opened, _, goal = self._events(td)
        env_r = td.get((keys.NEXT, keys.REWARD)).reshape(goal.shape).to(torch.float32)
        parts = [picked, opened, goal]
        return torch.stack([p.to(torch.float32) for p in parts] + [env_r], -1)

    def robustness_reward(self, td: TensorDictBase) -> torch.Tensor:
        picked, dropped, opened, closed, goal = self._events(td)
        f = lambda a, b: a.to(torch.float32) - b.to(torch.float32)  # noqa: E731
        r = [f(picked, dropped), f(opened, closed), goal.to(torch.float32)]
        return torch.stack(r + [r[0] + r[1] + r[2]], -1)


class LavaGapSubtasks(Subtasks):
    """to gap, to goal and the full task (module docstring)."""

    names = ("to_gap", "to_goal", "lavagap")
    hierarchy = Hierarchy(root="lavagap", children={"lavagap": ("to_gap", "to_goal")})

    def __init__(self, size: int):
        self.size = int(size)

    def initiation(self, td: TensorDictBase) -> torch.Tensor:
        side = td.get(SIDE)
        crossing = (side == GAP) | (side == RIGHT)
        return torch.stack([side == LEFT, crossing, torch.ones_like(crossing)], -1)

    def termination(self, td: TensorDictBase) -> torch.Tensor:
        end = _at_goal(td, self.size).unsqueeze(-1)
        beta = ~self.initiation(td) | end
        beta[..., -1] = False
        return beta

    def reward(self, td: TensorDictBase) -> torch.Tensor:
        nxt = td.get(keys.NEXT)
        gap = (nxt.get(SIDE) == GAP) & (td.get(SIDE) == LEFT)
        goal = _at_goal(nxt, self.size)
        env_r = nxt.get(keys.REWARD).reshape(goal.shape).to(torch.float32)
        return torch.stack([gap.to(torch.float32), goal.to(torch.float32), env_r], -1)

    def robustness_reward(self, td: TensorDictBase) -> torch.Tensor:
        nxt = td.get(keys.NEXT)
        side, side2 = td.get(SIDE), nxt.get(SIDE)
        lava = (side2 == LAVA).to(torch.float32)
        back = ((side != LEFT) & (side2 == LEFT)).to(torch.float32)  # back through the gap
        to_gap = ((side == LEFT) & (side2 == GAP)).to(torch.float32) - back - lava
        to_goal = _at_goal(nxt, self.size).to(torch.float32) - back - lava
        return torch.stack([to_gap, to_goal, to_gap + to_goal], -1)
