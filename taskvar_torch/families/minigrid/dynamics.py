"""MiniGrid's grid world as pure batched tensor functions (Farama ``minigrid`` 3.2: ``step``,
``gen_obs``, ``process_vis``), checked step for step against the package
(tests/families/minigrid/test_minigrid_parity.py).

State: ``grid (N, W * H, 3)`` uint8 (``Grid.encode()``, cell ``(x, y)`` at row ``x * H + y``,
without the agent); ``x, y, direction (N,)`` int64 (0 right, 1 down, 2 left, 3 up); ``carrying (N,
3)`` uint8 (``(0, 0, 0)``: nothing); ``step_count (N,)`` int64. Rules and observation are MiniGrid's
(docs/minigrid.md#the-family); a box's ``toggle`` is not ported.
"""

from __future__ import annotations

import torch

OBJECT_TO_IDX = {
    "unseen": 0,
    "empty": 1,
    "wall": 2,
    "floor": 3,
    "door": 4,
    "key": 5,
    "ball": 6,
    "box": 7,
    "goal": 8,
    "lava": 9,
    "agent": 10,
}
"""MiniGrid's object codes (``minigrid.core.constants``)."""
COLOR_TO_IDX = {"red": 0, "green": 1, "blue": 2, "purple": 3, "yellow": 4, "grey": 5}
STATE_TO_IDX = {"open": 0, "closed": 1, "locked": 2}
DIR_TO_VEC = ((1, 0), (0, 1), (-1, 0), (0, -1))
"""Direction ``d`` moves the agent by ``DIR_TO_VEC[d]`` ``(dx, dy)``: right, down, left, up."""
ACTIONS = ("left", "right", "forward", "pickup", "drop", "toggle", "done")
"""Action ``i`` is ``ACTIONS[i]`` (MiniGrid's ``Actions``)."""
NUM_ACTIONS = len(ACTIONS)
LEFT, RIGHT, FORWARD, PICKUP, DROP, TOGGLE, DONE = range(NUM_ACTIONS)
NUM_OBJECTS, NUM_COLORS, NUM_STATES = 11, 6, 3
VIEW = 7
"""Side of the agent's view (MiniGrid's ``agent_view_size``)."""

EMPTY = (OBJECT_TO_IDX["empty"], 0, 0)
WALL = (OBJECT_TO_IDX["wall"], COLOR_TO_IDX["grey"], 0)
GOAL = (OBJECT_TO_IDX["goal"], COLOR_TO_IDX["green"], 0)
LAVA = (OBJECT_TO_IDX["lava"], COLOR_TO_IDX["red"], 0)
KEY_YELLOW = (OBJECT_TO_IDX["key"], COLOR_TO_IDX["yellow"], 0)
DOOR_LOCKED_YELLOW = (OBJECT_TO_IDX["door"], COLOR_TO_IDX["yellow"], STATE_TO_IDX["locked"])

_OVERLAP = ("empty", "floor", "goal", "lava")  # and an open door
_PICKUP = ("key", "ball", "box")


def _isin(obj: torch.Tensor, names: tuple[str, ...]) -> torch.Tensor:
    out = torch.zeros_like(obj, dtype=torch.bool)
    for n in names:
        out |= obj == OBJECT_TO_IDX[n]
    return out


def _view_offsets() -> tuple[torch.Tensor, torch.Tensor]:
    """``(4, 7, 7)`` each: the world offset ``(dx, dy)`` from the agent of view cell ``(vx, vy)``
    for each direction: ``forward * (6 - vy) + right * (vx - 3)`` (``right = (-fy, fx)``), what
    MiniGrid's ``get_view_exts``, ``Grid.slice`` and ``rotate_left`` compute."""
    v = torch.arange(VIEW)
    vx, vy = v.view(VIEW, 1), v.view(1, VIEW)
    ox, oy = [], []
    for fx, fy in DIR_TO_VEC:
        rx, ry = -fy, fx
        ox.append(fx * (VIEW - 1 - vy) + rx * (vx - VIEW // 2))
        oy.append(fy * (VIEW - 1 - vy) + ry * (vx - VIEW // 2))
    return torch.stack(ox), torch.stack(oy)


_OFF_X, _OFF_Y = _view_offsets()


def cell_at(grid: torch.Tensor, height: int, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` encoding of cell ``(x, y)`` ``(N,)`` of each grid."""
    flat = (x * height + y).view(-1, 1, 1).expand(-1, 1, 3)
    return grid.gather(1, flat).squeeze(1)


def step(
    grid: torch.Tensor,  # (N, W * H, 3) uint8
    height: int,
    x: torch.Tensor,  # (N,) int64
    y: torch.Tensor,
    direction: torch.Tensor,
    carrying: torch.Tensor,  # (N, 3) uint8
    step_count: torch.Tensor,  # (N,) int64
    action: torch.Tensor,  # (N,) int64
    max_steps: int,
) -> tuple[torch.Tensor, ...]:
    """One MiniGrid step of every grid (``MiniGridEnv.step``).

    Returns new tensors ``(grid, x, y, direction, carrying, step_count, reward, terminated,
    truncated)``: reward ``1 - 0.9 * step_count / max_steps`` on the goal, else 0; ``terminated`` on
    the goal or lava; ``truncated`` at ``max_steps`` (as MiniGrid, even on a terminating step).
    """
    dev = grid.device
    dvec = torch.tensor(DIR_TO_VEC, device=dev)  # (4, 2)
    step_count = step_count + 1
    fx, fy = x + dvec[direction, 0], y + dvec[direction, 1]  # the walls keep these on the grid
    front = cell_at(grid, height, fx, fy)  # (N, 3)
    obj, colour, state = front.long().unbind(-1)
    is_door = obj == OBJECT_TO_IDX["door"]

    turn = (action == LEFT).long() * 3 + (action == RIGHT).long()
    direction = (direction + turn) % 4
    forward = action == FORWARD
    overlap = _isin(obj, _OVERLAP) | (is_door & (state == STATE_TO_IDX["open"]))
    move = forward & overlap
    x, y = torch.where(move, fx, x), torch.where(move, fy, y)
    goal = forward & (obj == OBJECT_TO_IDX["goal"])
    terminated = goal | (forward & (obj == OBJECT_TO_IDX["lava"]))
    success = 1.0 - 0.9 * (step_count.to(torch.float64) / max_steps)
    reward = torch.where(goal, success, 0.0).to(torch.float32)

    empty_hand = carrying[:, 0] == 0
    pick = (action == PICKUP) & _isin(obj, _PICKUP) & empty_hand
    drop = (action == DROP) & (obj == OBJECT_TO_IDX["empty"]) & ~empty_hand
    toggle = (action == TOGGLE) & is_door
    locked = state == STATE_TO_IDX["locked"]
    has_key = (carrying[:, 0].long() == OBJECT_TO_IDX["key"]) & (carrying[:, 1].long() == colour)
    unlock = toggle & locked & has_key
    flip = toggle & ~locked  # open <-> closed
    toggled = torch.where(unlock, STATE_TO_IDX["open"], 1 - state).to(grid.dtype)
    toggled = torch.cat([front[:, :2], toggled.unsqueeze(-1)], -1)
    empty = torch.tensor(EMPTY, dtype=grid.dtype, device=dev).expand_as(front)
    new_front = torch.where(pick.unsqueeze(-1), empty, front)
    new_front = torch.where(drop.unsqueeze(-1), carrying, new_front)
    new_front = torch.where((unlock | flip).unsqueeze(-1), toggled, new_front)
    flat = (fx * height + fy).view(-1, 1, 1).expand(-1, 1, 3)
    grid = grid.scatter(1, flat, new_front.unsqueeze(1))
    nothing = torch.zeros_like(carrying)
    carrying = torch.where(pick.unsqueeze(-1), front, carrying)
    carrying = torch.where(drop.unsqueeze(-1), nothing, carrying)

    truncated = step_count >= max_steps
    return grid, x, y, direction, carrying, step_count, reward, terminated, truncated


def transparent(cells: torch.Tensor) -> torch.Tensor:
    """``(...)`` bool: MiniGrid's ``see_behind`` of encoded cells ``(..., 3)``: every object but
    a wall and a door that is not open."""
    obj, state = cells[..., 0], cells[..., 2]
    door = obj == OBJECT_TO_IDX["door"]
    return ~((obj == OBJECT_TO_IDX["wall"]) | (door & (state != STATE_TO_IDX["open"])))


def visibility(see: torch.Tensor) -> torch.Tensor:
    """``(N, 7, 7)`` bool: MiniGrid's ``Grid.process_vis`` of a view from the agent at ``(3, 6)``
    (``see[:, vx, vy]``: see-through cells), in matrix form, one boolean product per row.
    """
    dev = see.device
    t = see.transpose(1, 2)  # (N, 7 rows vy, 7 columns vx)
    E = torch.nn.functional.pad((~t).to(torch.float32).cumsum(-1), (1, 0))  # opaque among < k
    col = torch.arange(VIEW, device=dev)
    right = (E[..., None, :VIEW] - E[..., :VIEW, None]) == 0  # [l, i]: l..i-1 see-through
    left = (E[..., 1:, None] - E[..., None, 1:]) == 0  # [l, i]: i+1..l see-through
    reach = torch.where(col.view(-1, 1) <= col.view(1, -1), right, left).to(torch.float32)
    spread = (col.view(-1, 1) - col.view(1, -1)).abs() <= 1  # a lit cell lights the 3 above
    up_reach = spread.to(torch.float32) @ reach[:, :-1]  # (N, 6, 7, 7): row j lit -> row j - 1
    rows = [reach[:, VIEW - 1, VIEW // 2] > 0]  # the agent's row
    for j in reversed(range(1, VIEW)):
        lit = (rows[-1] & t[:, j]).to(torch.float32).unsqueeze(1)  # (N, 1, 7)
        rows.append((lit @ up_reach[:, j - 1]).squeeze(1) > 0)
    return torch.stack(rows[::-1], 2)  # (N, vx, vy)


def view(
    grid: torch.Tensor,  # (N, W * H, 3) uint8
    width: int,
    height: int,
    x: torch.Tensor,
    y: torch.Tensor,
    direction: torch.Tensor,
    carrying: torch.Tensor,  # (N, 3) uint8
) -> torch.Tensor:
    """MiniGrid's ``image`` observation ``(N, 7, 7, 3)`` uint8, indexed ``[vx, vy, channel]`` as
    ``gen_obs`` returns it (module docstring)."""
    dev = grid.device
    off_x, off_y = _OFF_X.to(dev)[direction], _OFF_Y.to(dev)[direction]  # (N, 7, 7)
    wx, wy = x.view(-1, 1, 1) + off_x, y.view(-1, 1, 1) + off_y
    inside = (wx >= 0) & (wx < width) & (wy >= 0) & (wy < height)
    flat = (wx.clamp(0, width - 1) * height + wy.clamp(0, height - 1)).view(-1, VIEW * VIEW, 1)
    cells = grid.gather(1, flat.expand(-1, -1, 3)).view(-1, VIEW, VIEW, 3)
    wall = torch.tensor(WALL, dtype=grid.dtype, device=dev)
    cells = torch.where(inside.unsqueeze(-1), cells, wall)
    visible = visibility(transparent(cells))
    empty = torch.tensor(EMPTY, dtype=grid.dtype, device=dev)
    held = torch.where((carrying[:, :1] == 0), empty, carrying)  # (N, 3)
    cells = cells.clone()
    cells[:, VIEW // 2, VIEW - 1] = held
    return torch.where(visible.unsqueeze(-1), cells, torch.zeros_like(cells))
