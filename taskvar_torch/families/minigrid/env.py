"""TorchRL ``EnvBase`` over the batched MiniGrid dynamics (``dynamics.py``) and layouts
(``layouts.py``)."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from taskvar_torch import keys
from taskvar_torch.envs.batched import BatchedFamilyEnv
from taskvar_torch.families.minigrid import dynamics as D
from taskvar_torch.families.minigrid.layouts import (
    DEFAULT_MAX_STEPS,
    INSTANCE_NAMES,
    LayoutSampler,
    check_task,
)

OBS_ENCODINGS = ("onehot", "image")
CARRYING, DOOR, SIDE = "carrying", "door", "side"
"""Integer state beside the observation that the options read (``subtasks.py``): the carried
object's type (0: nothing), the door's state (DoorKey; 0 open, 1 closed, 2 locked; LavaGap: 0)
and where the agent is against the splitting column (:data:`SIDES`)."""
SIDES = ("left", "gap", "right", "lava")
"""``side``: left of the splitting wall or lava column, in its door or gap, right of it, or on
lava (the episode's end)."""
PARAMS = 4
"""Columns of ``("instance", "params")``: DoorKey's wall column, door row, key x and y;
LavaGap's gap x and y, then zeros."""
ONEHOT_CHANNELS = D.NUM_OBJECTS + D.NUM_STATES


def observation_size(encoding: str) -> int:
    """``D`` of :func:`encode`: the direction one-hot (4) and the view's channels."""
    channels = {"onehot": ONEHOT_CHANNELS, "image": 3}[encoding]
    return 4 + channels * D.VIEW * D.VIEW


def encode(image: torch.Tensor, direction: torch.Tensor, encoding: str = "onehot") -> torch.Tensor:
    """The ``(N, D)`` float32 observation of MiniGrid's ``image (N, 7, 7, 3)`` and ``direction
    (N,)``: the direction one-hot (4), then the view channel-major ``(C, vy, vx)``, ``onehot``
    (object type and door state, C = 14) or ``image`` (the three codes, C = 3). Also encodes the
    package's own observations.
    """
    image = torch.as_tensor(image).long().permute(0, 3, 2, 1)  # (N, 3, vy, vx)
    direction = torch.as_tensor(direction).long().view(-1)
    compass = torch.nn.functional.one_hot(direction, 4).to(torch.float32)
    if encoding == "image":
        view = image.to(torch.float32)
    elif encoding == "onehot":
        obj = torch.nn.functional.one_hot(image[:, 0], D.NUM_OBJECTS)  # (N, vy, vx, 11)
        state = torch.nn.functional.one_hot(image[:, 2], D.NUM_STATES)
        view = torch.cat([obj, state], -1).permute(0, 3, 1, 2).to(torch.float32)
    else:
        raise ValueError(f"obs_encoding must be one of {list(OBS_ENCODINGS)}, got {encoding!r}")
    return torch.cat([compass, view.flatten(1)], -1)


class MiniGridEnv(BatchedFamilyEnv):
    """Batched MiniGrid (DoorKey or LavaGap) with a hidden layout, as a TorchRL environment.

    ## Description MiniGrid's ``MiniGrid-DoorKey-{5,6,8}x...`` and ``MiniGrid-LavaGapS{5,6,7}``
    ported step for step (docs/minigrid.md#the-family); each sub-environment draws its hidden layout
    at every reset.

    ## Action Space ``Categorical(7)``: 0 left, 1 right, 2 forward, 3 pickup, 4 drop, 5 toggle, 6
    done.

    ## Observation Space ``observation`` (:func:`encode`; ``onehot`` 690 or ``image`` 151 floats);
    ``cell`` the pose ``(x * H + y) * 4 + direction``; ``carrying``, ``door``, ``side``; for
    analysis only ``("instance", "layout" | "params")``.

    ## Reward ``1 - 0.9 * step_count / max_steps`` on reaching the goal, else 0.

    ## Episode End Terminated on the goal or lava; truncated after ``max_steps``.

    Args:
        num_envs: batch size N.
        task: ``doorkey`` or ``lavagap``.
        size: grid side.
        max_steps: steps before truncation; ``None``: MiniGrid's default.
        obs_encoding: ``onehot`` or ``image``.
        instances: ``train``, ``heldout`` or ``minigrid``.
        seed, index_offset: sub-environment ``i`` draws from key ``(seed, index_offset + i)``.
        noise_seed: unused (the dynamics are deterministic given the layout).
        validate_actions: check actions are in range (one host sync a step); ``None``: on CPU.
        device: torch device.
    """

    runtime_state = (
        "_base_key",
        "_episode",
        "_grid",
        "_x",
        "_y",
        "_dir",
        "_carrying",
        "_t",
        "_layout",
    )

    def state_bounds(self) -> dict[str, tuple[float, float]]:
        return {
            **super().state_bounds(),
            "x": (1, self.size - 2),
            "y": (1, self.size - 2),
            "dir": (0, 3),
            "t": (0, self.horizon),
            "layout": (0, self.sampler.table.num_layouts - 1),
            "grid": (0, D.NUM_OBJECTS - 1),
            "carrying": (0, D.NUM_OBJECTS - 1),
        }

    def __init__(
        self,
        num_envs: int = 1,
        task: str = "doorkey",
        size: int = 5,
        max_steps: int | None = None,
        obs_encoding: str = "onehot",
        instances: str = "train",
        seed: int = 0,
        index_offset: int = 0,
        noise_seed: int = 0,
        validate_actions: bool | None = None,
        device: torch.device | str = "cpu",
    ):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        check_task(task, size)
        if obs_encoding not in OBS_ENCODINGS:
            raise ValueError(
                f"obs_encoding must be one of {list(OBS_ENCODINGS)}, got {obs_encoding!r}"
            )
        if not isinstance(instances, str) or instances not in INSTANCE_NAMES:
            raise ValueError(f"instances must be one of {list(INSTANCE_NAMES)}, got {instances!r}")
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        self.task, self.size, self.obs_encoding = task, int(size), obs_encoding
        self.horizon = (
            DEFAULT_MAX_STEPS[task] * self.size**2 if max_steps is None else int(max_steps)
        )
        if self.horizon < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.instances = instances
        self.sampler = LayoutSampler(task, self.size, instances, self.device)
        self.index_offset = int(index_offset)
        self.noise_seed = int(noise_seed)
        self.validate_actions = (
            self.device.type == "cpu" if validate_actions is None else bool(validate_actions)
        )
        self._make_specs()
        self._set_seed(seed)

    def _make_specs(self) -> None:
        N, dev = self.num_envs, self.device
        M = self.sampler.table.num_layouts
        D_obs = observation_size(self.obs_encoding)
        high = 1.0 if self.obs_encoding == "onehot" else float(D.NUM_OBJECTS - 1)
        cat = lambda n: Categorical(n, shape=(N,), dtype=torch.int64, device=dev)  # noqa: E731
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: Bounded(
                    0.0, high, shape=(N, D_obs), dtype=torch.float32, device=dev
                ),
                keys.CELL: cat(self.size * self.size * 4),
                CARRYING: cat(D.NUM_OBJECTS),
                DOOR: cat(D.NUM_STATES),
                SIDE: cat(len(SIDES)),
                keys.INSTANCE: Composite(
                    layout=cat(M),
                    params=Bounded(
                        0, self.size - 1, shape=(N, PARAMS), dtype=torch.int64, device=dev
                    ),
                    shape=(N,),
                    device=dev,
                ),
            },
            shape=(N,),
            device=dev,
        )
        self.action_spec = Categorical(D.NUM_ACTIONS, shape=(N,), dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(N, 1), dtype=torch.float32, device=dev)
        self.make_done_spec()

    # ---- state read-outs -------------------------------------------------------------------

    def params(self) -> torch.Tensor:
        """``(N, 4)`` int64 layout parameters (:data:`PARAMS`)."""
        p = self.sampler.params.index_select(0, self._layout)
        return torch.nn.functional.pad(p, (0, PARAMS - p.shape[1]))

    def image(self) -> torch.Tensor:
        """MiniGrid's ``image`` observation ``(N, 7, 7, 3)`` uint8 of every sub-environment."""
        return D.view(self._grid, self.size, self.size, self._x, self._y, self._dir, self._carrying)

    def _side(self, params: torch.Tensor) -> torch.Tensor:
        col, row = params[:, 0], params[:, 1]
        on_column = self._x == col
        side = torch.where(self._x < col, 0, torch.where(on_column, 1, 2))
        if self.task == "lavagap":
            side = torch.where(on_column & (self._y != row), 3, side)
        return side

    def _out(self, reward=None, terminated=None, truncated=None) -> TensorDictBase:
        params = self.params()
        H = self.size
        if self.task == "doorkey":  # the door's state, read off the grid
            door = D.cell_at(self._grid, H, params[:, 0], params[:, 1])[:, 2].long()
        else:
            door = torch.zeros_like(self._x)
        instance = {"layout": self._layout, "params": params}
        td = {
            keys.OBSERVATION: encode(self.image(), self._dir, self.obs_encoding),
            keys.CELL: (self._x * H + self._y) * 4 + self._dir,
            CARRYING: self._carrying[:, 0].long(),
            DOOR: door,
            SIDE: self._side(params),
            keys.INSTANCE: TensorDict._new_unsafe(
                instance, batch_size=self.batch_size, device=self.device
            ),
        }
        return self.finish(td, reward, terminated, truncated)

    # ---- TorchRL hooks -----------------------------------------------------------------------

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        idx, key = self.next_episodes(tensordict, hasattr(self, "_grid"))
        drawn = self.sampler.draw(key)
        new = {
            "_grid": drawn["grid"],
            "_x": drawn["x"],
            "_y": drawn["y"],
            "_dir": drawn["direction"],
            "_carrying": torch.zeros(key.shape[0], 3, dtype=torch.uint8, device=self.device),
            "_t": torch.zeros_like(drawn["x"]),
            "_layout": drawn["layout"],
        }
        if idx is not None:  # out of place: tensors already handed out are never mutated
            new = {k: getattr(self, k).index_put((idx,), v) for k, v in new.items()}
        self.replace_state(new)
        return self._out()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION).reshape(-1)
        if self.validate_actions and bool(((action < 0) | (action >= D.NUM_ACTIONS)).any()):
            bad = action[(action < 0) | (action >= D.NUM_ACTIONS)][0].item()
            raise ValueError(f"action must be in [0, {D.NUM_ACTIONS - 1}], got {bad}")
        grid, x, y, d, carrying, t, reward, terminated, truncated = D.step(
            self._grid,
            self.size,
            self._x,
            self._y,
            self._dir,
            self._carrying,
            self._t,
            action,
            self.horizon,
        )
        self.replace_state(
            {"_grid": grid, "_x": x, "_y": y, "_dir": d, "_carrying": carrying, "_t": t}
        )
        truncated = truncated & ~terminated
        return self._out(reward.unsqueeze(-1), terminated.unsqueeze(-1), truncated.unsqueeze(-1))

    def set_state(self, grid, x, y, direction, carrying, step_count, layout=None) -> None:
        """Install a state (``dynamics`` docstring), e.g. one copied from the ``minigrid``
        package's env (the parity tests); ``layout``: the hidden layout index (default: kept)."""
        as_long = lambda v: torch.as_tensor(v, device=self.device).long().view(-1)  # noqa: E731
        state = {
            "_grid": torch.as_tensor(grid, device=self.device)
            .to(torch.uint8)
            .view(self.num_envs, -1, 3),
            "_x": as_long(x),
            "_y": as_long(y),
            "_dir": as_long(direction),
            "_carrying": torch.as_tensor(carrying, device=self.device).to(torch.uint8).view(-1, 3),
            "_t": as_long(step_count),
        }
        if layout is not None:
            state["_layout"] = as_long(layout)
        self.replace_state(state)

    def render(self, index: int = 0, mode: str = "ansi"):
        """Sub-environment ``index`` as text (``ansi``: MiniGrid's ``pprint_grid`` letters) or an
        image (``rgb_array``: one flat tile a cell, the agent a red square)."""
        grid, x, y = self._grid[index], int(self._x[index]), int(self._y[index])
        if mode == "ansi":
            return render_ansi(grid, self.size, x, y, int(self._dir[index]))
        if mode == "rgb_array":
            return render_rgb(grid, self.size, x, y)
        raise ValueError(f"render mode must be one of ['ansi', 'rgb_array'], got {mode!r}")


def render_ansi(grid: torch.Tensor, size: int, x: int, y: int, direction: int) -> str:
    """MiniGrid's ``pprint_grid`` of one grid ``(W * H, 3)``: two characters a cell."""
    letters = {2: "W", 3: "F", 4: "D", 5: "K", 6: "A", 7: "B", 8: "G", 9: "V"}
    colours = "RGBPYG"
    cells = grid.view(size, size, 3).tolist()
    lines = []
    for j in range(size):
        row = ""
        for i in range(size):
            obj, col, state = cells[i][j]
            if (i, j) == (x, y):
                row += 2 * ">V<^"[direction]
            elif obj == 1:
                row += "  "
            elif obj == 4:
                row += "__" if state == 0 else ("L" if state == 2 else "D") + colours[col]
            else:
                row += letters[obj] + colours[col]
        lines.append(row)
    return "\n".join(lines)


COLOURS = np.array(
    [[255, 0, 0], [0, 255, 0], [0, 0, 255], [112, 39, 195], [255, 255, 0], [100, 100, 100]],
    dtype=np.uint8,
)
"""MiniGrid's colours by index (``minigrid.core.constants.COLORS``)."""
TILE = 16


def render_rgb(grid: torch.Tensor, size: int, x: int, y: int) -> np.ndarray:
    """A ``(size * TILE, size * TILE, 3)`` uint8 image of one grid ``(W * H, 3)``: each object a
    flat tile of its colour, the agent a red one, grid lines grey."""
    cells = grid.view(size, size, 3).numpy()
    img = COLOURS[cells[..., 1]] * (cells[..., :1] > D.OBJECT_TO_IDX["empty"])
    img[x, y] = (255, 0, 0)
    img = img.transpose(1, 0, 2).repeat(TILE, 0).repeat(TILE, 1)  # rows are y
    img[::TILE], img[:, ::TILE] = 100, 100  # grid lines
    return np.ascontiguousarray(img, dtype=np.uint8)
