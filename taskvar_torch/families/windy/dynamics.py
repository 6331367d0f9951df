"""Windy gridworld family (paper §3.3.1): layouts, pure batched dynamics, exact model.

Cells are flat indices ``row * width + col`` (row 0 is north). A step is one gather in
``next[cell, action, direction, gust]`` (the move, then at most one gust where the move ends in a
windy cell); ``gust`` is the caller's Bernoulli(p) draw (``rng.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

ACTIONS = ("north", "south", "east", "west")
"""Action ``i`` moves one cell in ``ACTIONS[i]``; wind direction indices use the same order."""
DIRECTIONS = ACTIONS
_DELTAS = ((-1, 0), (1, 0), (0, 1), (0, -1))  # (drow, dcol) per action / wind direction
_CELL_CHARS = {"S": "start", "W": "windy", "#": "wall", "G": "goal", ".": "free"}

DEFAULT_MAP = """
S W . G G
S . # G G
S . # G G
S . # G G
S W . G G
"""
"""The default layout: a wall in column 2 with exits on the border rows, wind just west of them."""

MIDDLE_EXITS_MAP = """
S . # G G
S W . G G
S . # G G
S W . G G
S . # G G
"""
"""The "middle exits" reading of the paper's Figure 1: exits at rows 1 and 3."""

WHOLE_COLUMN_WINDY_MAP = """
S W . G G
S W # G G
S W # G G
S W # G G
S W . G G
"""
"""Border exits with every cell of column 1 windy: interruption changes behaviour here."""

LAYOUTS = {
    "default": DEFAULT_MAP,
    "middle_exits": MIDDLE_EXITS_MAP,
    "whole_column_windy": WHOLE_COLUMN_WINDY_MAP,
}


def direction_index(direction: str | int) -> int:
    """Index of a wind direction name (``"north"``...) or a validated index."""
    if isinstance(direction, str):
        name = direction.lower()
        if name not in DIRECTIONS:
            raise ValueError(f"direction must be one of {list(DIRECTIONS)}, got {direction!r}")
        return DIRECTIONS.index(name)
    if isinstance(direction, (int, np.integer)) and 0 <= int(direction) < len(DIRECTIONS):
        return int(direction)
    raise ValueError(
        f"direction must be one of {list(DIRECTIONS)} (or an index 0..3), got {direction!r}"
    )


@dataclass(frozen=True)
class WindyLayout:
    """A parsed map: rows of ``S`` start, ``W`` windy, ``#`` wall, ``G`` goal, ``.`` free."""

    rows: tuple[str, ...]

    @classmethod
    def from_map(cls, text: str) -> WindyLayout:
        """Parse a map string (cells separated by spaces or not); raises ``ValueError`` naming the problem."""
        if not isinstance(text, str):
            raise ValueError(f"map must be a string, got {type(text).__name__}")
        rows = [line.replace(" ", "").strip() for line in text.strip().splitlines()]
        rows = [r for r in rows if r]
        if not rows:
            raise ValueError("map is empty: expected rows of S, W, #, G, .")
        width = len(rows[0])
        for i, r in enumerate(rows):
            if len(r) != width:
                raise ValueError(
                    f"map row {i} has {len(r)} cells, expected {width}: every row must be equally long"
                )
            bad = sorted(set(r) - set(_CELL_CHARS))
            if bad:
                raise ValueError(
                    f"map row {i} has unknown cell characters {bad}; allowed: {sorted(_CELL_CHARS)}"
                )
        layout = cls(tuple(rows))
        if not any("S" in r for r in rows):
            raise ValueError("map has no start cell 'S'")
        if not any("G" in r for r in rows):
            raise ValueError("map has no goal cell 'G'")
        if layout.num_exits < 1:
            raise ValueError("map has no exit: no free cell is next to a goal cell")
        return layout

    @classmethod
    def named(cls, name: str) -> WindyLayout:
        """One of the shipped layouts: ``default``, ``middle_exits``, ``whole_column_windy``."""
        if name not in LAYOUTS:
            raise ValueError(
                f"layout must be one of {sorted(LAYOUTS)} or a map string, got {name!r}"
            )
        return cls.from_map(LAYOUTS[name])

    @property
    def height(self) -> int:
        return len(self.rows)

    @property
    def width(self) -> int:
        return len(self.rows[0])

    @property
    def num_cells(self) -> int:
        return self.height * self.width

    def char(self, cell: int) -> str:
        return self.rows[cell // self.width][cell % self.width]

    def cells_of(self, ch: str) -> list[int]:
        return [c for c in range(self.num_cells) if self.char(c) == ch]

    def neighbour(self, cell: int, d: int) -> int:
        """Cell reached from ``cell`` moving in direction ``d``; walls and edges leave it in place."""
        r, c = divmod(cell, self.width)
        dr, dc = _DELTAS[d]
        r2, c2 = r + dr, c + dc
        if not (0 <= r2 < self.height and 0 <= c2 < self.width) or self.rows[r2][c2] == "#":
            return cell
        return r2 * self.width + c2

    @property
    def exit_cells(self) -> list[list[int]]:
        """Exits: connected groups of non-goal, non-wall cells next to a goal cell, ordered by row."""
        # the cells next to a goal, found on the whole grid at once (a map of millions of cells
        # in a second); the groups below walk the exits only
        grid = np.frombuffer("".join(self.rows).encode("ascii"), np.uint8)
        grid = grid.reshape(self.height, self.width)
        goal = grid == ord("G")
        near = np.zeros_like(goal)
        near[1:] |= goal[:-1]
        near[:-1] |= goal[1:]
        near[:, 1:] |= goal[:, :-1]
        near[:, :-1] |= goal[:, 1:]
        free = ~goal & (grid != ord("#"))
        is_exit = set(np.flatnonzero(free & near).tolist())
        groups: list[list[int]] = []
        seen: set[int] = set()
        for cell in sorted(is_exit):
            if cell in seen:
                continue
            stack, group = [cell], []
            seen.add(cell)
            while stack:
                c = stack.pop()
                group.append(c)
                for d in range(4):
                    n = self.neighbour(c, d)
                    if n in is_exit and n not in seen:
                        seen.add(n)
                        stack.append(n)
            groups.append(sorted(group))
        return groups

    @property
    def num_exits(self) -> int:
        return len(self.exit_cells)

    @property
    def exit_names(self) -> tuple[str, ...]:
        """``exit_north``/``exit_south`` for two exits, else ``exit_0``... by row."""
        n = self.num_exits
        if n == 2:
            return ("exit_north", "exit_south")
        return tuple(f"exit_{k}" for k in range(n))

    def render_text(self, cell: int | None = None) -> str:
        """The map as text, with ``A`` at ``cell``."""
        out = []
        for r, row in enumerate(self.rows):
            chars = list(row)
            if cell is not None and cell // self.width == r:
                chars[cell % self.width] = "A"
            out.append(" ".join(chars))
        return "\n".join(out) + "\n"


def make_layout(
    height: int,
    width: int,
    num_exits: int = 2,
    wall_col: int | None = None,
    wind_cells_per_exit: int = 1,
) -> WindyLayout:
    """Scaled-up generator (docs/scale.md): a full-height wall with ``num_exits`` one-cell gaps,
    ``wind_cells_per_exit`` windy cells west of each, start column west, goal east of the wall.
    """
    if num_exits < 2:
        raise ValueError(f"num_exits must be >= 2, got {num_exits}")
    if wall_col is None:
        wall_col = width // 2
    if height < num_exits:
        raise ValueError(f"height must be >= num_exits ({num_exits}), got {height}")
    if not (1 + wind_cells_per_exit <= wall_col <= width - 2):
        raise ValueError(
            f"wall_col must be in [{1 + wind_cells_per_exit}, {width - 2}] for width {width} and "
            f"wind_cells_per_exit {wind_cells_per_exit}, got {wall_col}"
        )
    if wind_cells_per_exit < 0:
        raise ValueError(f"wind_cells_per_exit must be >= 0, got {wind_cells_per_exit}")
    exit_rows = sorted({round(k * (height - 1) / (num_exits - 1)) for k in range(num_exits)})
    if len(exit_rows) != num_exits:
        raise ValueError(f"height {height} too small for {num_exits} distinct exits")
    grid = [["."] * width for _ in range(height)]
    for r in range(height):
        grid[r][0] = "S"
        grid[r][wall_col] = "." if r in exit_rows else "#"
        for c in range(wall_col + 1, width):
            grid[r][c] = "G"
    for r in exit_rows:
        for k in range(1, wind_cells_per_exit + 1):
            grid[r][wall_col - k] = "W"
    return WindyLayout(tuple("".join(row) for row in grid))


def default_horizon(layout: WindyLayout) -> int:
    """100 steps on the paper's 5x5 grid, growing with size: ``max(100, 4 * (height + width))``."""
    return max(100, 4 * (layout.height + layout.width))


class WindyModel:
    """Lookup tables of one layout on one device: ``move (S, A)``, ``push (S, D)`` (the cell itself
    where not windy), ``is_goal``, ``is_windy``, ``exit_id (S,)`` (-1: no exit), ``start_cells
    (K,)``."""

    def __init__(self, layout: WindyLayout, device: torch.device | str = "cpu"):
        self.layout = layout
        self.device = torch.device(device)
        S, A = layout.num_cells, len(ACTIONS)
        move = np.array([[layout.neighbour(c, a) for a in range(A)] for c in range(S)])
        windy = np.array([layout.char(c) == "W" for c in range(S)])
        push = np.array(
            [[layout.neighbour(c, d) if windy[c] else c for d in range(A)] for c in range(S)]
        )
        exit_id = np.full(S, -1)
        for k, group in enumerate(layout.exit_cells):
            exit_id[group] = k
        t = dict(dtype=torch.int64, device=self.device)
        self.move = torch.as_tensor(move, **t)
        self.push = torch.as_tensor(push, **t)
        # next_flat[((cell * 4 + action) * 4 + direction) * 2 + gust]: the whole step in one table
        nxt = np.stack([np.broadcast_to(move[:, :, None], (S, A, A)), push[move]], axis=-1)
        self.next_flat = torch.as_tensor(nxt.reshape(-1).copy(), **t)
        goal = [layout.char(c) == "G" for c in range(S)]
        self.is_goal = torch.tensor(goal, device=self.device)
        self.is_windy = torch.as_tensor(windy, device=self.device)
        self.exit_id = torch.as_tensor(exit_id, **t)
        self.start_cells = torch.tensor(layout.cells_of("S"), **t)
        self.num_cells, self.num_actions = S, A


def step(
    model: WindyModel,
    cell: torch.Tensor,  # (B,) int64
    action: torch.Tensor,  # (B,) int64
    direction: torch.Tensor,  # (B,) int64
    gust: torch.Tensor,  # (B,) bool: the wind blows this step (a Bernoulli(p) draw)
) -> tuple[torch.Tensor, torch.Tensor]:
    """One batched step (move, then at most one gust): ``(next_cell, terminated)``; reward -1 per
    step."""
    idx = torch.add(gust, direction, alpha=2).add_(action, alpha=8).add_(cell, alpha=32)  # (B,)
    nxt = model.next_flat.index_select(0, idx)  # (B,)
    return nxt, model.is_goal.index_select(0, nxt)


def transition_tensors(
    model: WindyModel,
    p: torch.Tensor,  # (B,) float
    direction: torch.Tensor,  # (B,) int64
    dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact model ``P[B, S, A, S']`` and ``R[B, S, A]`` of :func:`step`'s dynamics; goal cells
    absorb with reward 0, every other action costs -1."""
    p = torch.as_tensor(p, dtype=dtype, device=model.device).reshape(-1)
    direction = torch.as_tensor(direction, dtype=torch.int64, device=model.device).reshape(-1)
    B, S, A = p.shape[0], model.num_cells, model.num_actions
    moved = model.move.unsqueeze(0).expand(B, S, A)  # (B, S, A)
    gust = model.push[moved, direction.view(B, 1, 1)]  # (B, S, A)
    P = torch.zeros(B, S, A, S, dtype=dtype, device=model.device)
    pp = p.view(B, 1, 1).expand(B, S, A)
    P.scatter_add_(3, moved.unsqueeze(-1), (1.0 - pp).unsqueeze(-1))
    P.scatter_add_(3, gust.unsqueeze(-1), pp.unsqueeze(-1))
    goal = model.is_goal
    P[:, goal] = 0.0
    goal_idx = goal.nonzero().squeeze(-1)
    P[:, goal_idx, :, goal_idx] = 1.0
    R = torch.full((B, S, A), -1.0, dtype=dtype, device=model.device)
    R[:, goal] = 0.0
    return P, R
