"""The hidden layouts of the MiniGrid family (paper §2: the hidden parameter is the layout): every
layout MiniGrid's ``_gen_grid`` can draw, its probability there, and the sealed train / held-out
split by a hash of each layout (docs/minigrid.md#the-family).

A layout is DoorKey's wall column, door row and key cell, or LavaGap's gap cell; the start is drawn
given it, as MiniGrid draws it. A draw is an inverse-CDF lookup of a 24-bit uniform from the episode
key (:mod:`taskvar_torch.rng`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from taskvar_torch import rng
from taskvar_torch.families.minigrid import dynamics as D

TASKS = ("doorkey", "lavagap")
INSTANCE_NAMES = ("train", "heldout", "minigrid")
HELDOUT_SHARE = 5
"""One layout in this many (rounded up) is held out."""
_SPLIT_SALT = 0x4D475244  # fixes which layouts are held out; never tuned
_C_LAYOUT, _C_CELL, _C_DIR = rng.RESET_COUNTER, rng.RESET_COUNTER + 1, rng.RESET_COUNTER + 2
MIN_SIZE = {"doorkey": 5, "lavagap": 5}
MAX_SIZE = 16
DEFAULT_MAX_STEPS = {"doorkey": 10, "lavagap": 4}
"""MiniGrid's ``max_steps`` is this times ``size ** 2``."""


def check_task(task: str, size: int) -> None:
    """One-line ``ValueError`` unless ``task`` is one of :data:`TASKS` and ``size`` fits it."""
    if task not in TASKS:
        raise ValueError(f"task must be one of {list(TASKS)}, got {task!r}")
    if not MIN_SIZE[task] <= int(size) <= MAX_SIZE:
        raise ValueError(f"size must be in [{MIN_SIZE[task]}, {MAX_SIZE}] for {task}, got {size}")


@dataclass(frozen=True)
class Layouts:
    """Every layout of ``task`` at ``size``: ``params (M, k)`` int64 (DoorKey: wall column, door
    row, key x, key y; LavaGap: gap x, gap y), MiniGrid's probability ``prob (M,)`` and the
    ``heldout (M,)`` mask."""

    task: str
    size: int
    params: np.ndarray
    prob: np.ndarray
    heldout: np.ndarray

    @property
    def num_layouts(self) -> int:
        return len(self.params)

    def probabilities(self, name: str) -> np.ndarray:
        """``(M,)`` the probability of each layout under the named distribution."""
        if name not in INSTANCE_NAMES:
            raise ValueError(f"instances must be one of {list(INSTANCE_NAMES)}, got {name!r}")
        keep = {"minigrid": np.ones_like(self.heldout), "train": ~self.heldout}
        p = self.prob * keep.get(name, self.heldout)
        return p / p.sum()


def layout_hash(params: np.ndarray) -> np.ndarray:
    """``(M,)`` 32-bit hash of each layout's parameters (which side of the split it falls)."""
    h = np.full(len(params), _SPLIT_SALT, dtype=np.int64)
    for col in params.T:
        h = rng.hash32((h ^ rng.hash32(col.astype(np.int64) + 0x9E37)) & rng.MASK32)
    return h


def layouts(task: str, size: int) -> Layouts:
    """Every layout of ``task`` on a ``size`` x ``size`` grid, with MiniGrid's probabilities."""
    check_task(task, size)
    W = H = int(size)
    rows, prob = [], []
    if task == "doorkey":
        for s in range(2, W - 2):
            room = (s - 1) * (H - 2)
            for door in range(1, H - 2):
                for kx in range(1, s):
                    for ky in range(1, H - 1):
                        rows.append((s, door, kx, ky))
                        prob.append(1.0 / ((W - 4) * (H - 3) * room))
    else:
        for gx in range(2, W - 2):
            for gy in range(1, H - 1):
                rows.append((gx, gy))
                prob.append(1.0 / ((W - 4) * (H - 2)))
    params = np.array(rows, dtype=np.int64)
    order = np.argsort(layout_hash(params), kind="stable")
    heldout = np.zeros(len(params), dtype=bool)
    heldout[order[: math.ceil(len(params) / HELDOUT_SHARE)]] = True
    return Layouts(task, W, params, np.array(prob), heldout)


def build_grids(task: str, size: int, params: torch.Tensor) -> torch.Tensor:
    """``(n, W * H, 3)`` uint8 grids (MiniGrid's encoding, ``dynamics`` docstring) of layouts
    ``params (n, k)``, as ``_gen_grid`` builds them."""
    W = H = int(size)
    n, dev = params.shape[0], params.device
    x = torch.arange(W, device=dev).view(1, W, 1)
    y = torch.arange(H, device=dev).view(1, 1, H)
    border = (x == 0) | (x == W - 1) | (y == 0) | (y == H - 1)

    def put(grid, where, obj):
        return torch.where(
            where.unsqueeze(-1), torch.tensor(obj, dtype=torch.uint8, device=dev), grid
        )

    grid = torch.tensor(D.EMPTY, dtype=torch.uint8, device=dev).expand(n, W, H, 3)
    grid = put(grid, border.expand(n, W, H), D.WALL)
    grid = put(grid, ((x == W - 2) & (y == H - 2)).expand(n, W, H), D.GOAL)
    p = params.view(n, -1, 1, 1)
    if task == "doorkey":
        s, door, kx, ky = p.unbind(1)
        grid = put(grid, (x == s) & (y != door), D.WALL)  # the wall, top to bottom
        grid = put(grid, (x == s) & (y == door), D.DOOR_LOCKED_YELLOW)
        grid = put(grid, (x == kx) & (y == ky), D.KEY_YELLOW)
    else:
        gx, gy = p.unbind(1)
        grid = put(grid, (x == gx) & (y >= 1) & (y <= H - 2) & (y != gy), D.LAVA)
    return grid.reshape(n, W * H, 3).contiguous()


class LayoutSampler:
    """Draws episodes' layouts and starts from keys on ``device``; ``instances``: ``train``,
    ``heldout`` or ``minigrid``.
    """

    def __init__(self, task: str, size: int, instances: str, device: torch.device | str = "cpu"):
        self.table = layouts(task, size)
        self.task, self.size, self.instances = task, int(size), instances
        cdf = np.cumsum(self.table.probabilities(instances))
        thresholds = np.minimum(np.round(cdf * (1 << 24)), 1 << 24).astype(np.int64)
        self._thresholds = torch.as_tensor(thresholds, device=device)
        self.params = torch.as_tensor(self.table.params, device=device)
        """``(M, k)`` every layout's parameters, on ``device``."""

    def draw(self, key: torch.Tensor) -> dict[str, torch.Tensor]:
        """The layout index ``(n,)``, grids ``(n, W * H, 3)``, start ``x, y, direction (n,)``
        drawn from episode keys ``(n,)``."""
        counters = torch.tensor([[_C_LAYOUT], [_C_CELL], [_C_DIR]], device=key.device)
        bits = rng.draw_bits(key, counters)  # (3, n)
        u = bits[0] >> 8  # uniform on [0, 2^24)
        index = torch.searchsorted(self._thresholds, u, right=True).clamp(max=len(self.params) - 1)
        params = self.params.index_select(0, index)  # (n, k)
        grid = build_grids(self.task, self.size, params)
        if self.task == "doorkey":
            H = self.size
            s, _, kx, ky = params.unbind(1)
            room = (s - 1) * (H - 2)  # free cells left of the wall, column by column
            a = rng.index_of(bits[1], room - 1)
            key_cell = (kx - 1) * (H - 2) + (ky - 1)
            a = a + (a >= key_cell).long()  # skip the key's cell
            x, y = 1 + a // (H - 2), 1 + a % (H - 2)
            direction = rng.index_of(bits[2], 4)
        else:
            x = torch.ones_like(index)
            y, direction = x.clone(), torch.zeros_like(index)
        return {"layout": index, "grid": grid, "x": x, "y": y, "direction": direction}
