"""Wargus rendering, numpy only: a text grid (``ansi``: ``A`` agent, ``P`` patrol, ``I`` item,
``*`` shoot range, ``+`` sight) and a uint8 image (``rgb_array``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from taskvar_torch.families.wargus.dynamics import WargusConfig

RENDER_MODES = ("ansi", "rgb_array")

_BG = np.array([246, 246, 240], dtype=np.float32)
_AGENT_SIGHT = np.array([222, 234, 252], dtype=np.float32)
_PATROL_SIGHT = np.array([250, 214, 210], dtype=np.float32)
_PATROL_SHOOT = np.array([238, 150, 138], dtype=np.float32)
_GRID = np.array([210, 210, 205], dtype=np.uint8)
_AGENT = np.array([30, 80, 200], dtype=np.uint8)
_PATROL = np.array([150, 15, 20], dtype=np.uint8)
_ITEM = np.array([225, 170, 10], dtype=np.uint8)


@dataclass(frozen=True)
class Frame:
    """What one sub-environment looks like at one time step (numpy, ``(row, col)`` int)."""

    config: WargusConfig
    agent: np.ndarray  # (2,)
    patrols: np.ndarray  # (K, 2)
    items: np.ndarray  # (M, 2)
    t: int = 0
    seed: int | None = None

    @classmethod
    def from_tensors(
        cls,
        config: WargusConfig,
        agent: torch.Tensor,  # (2,)
        patrols: torch.Tensor,  # (K, 2)
        items: torch.Tensor,  # (M, 2)
        t: int = 0,
        seed: int | None = None,
    ) -> Frame:
        return cls(
            config,
            agent.detach().cpu().numpy().astype(np.int64),
            patrols.detach().cpu().numpy().astype(np.int64).reshape(-1, 2),
            items.detach().cpu().numpy().astype(np.int64).reshape(-1, 2),
            t,
            seed,
        )


def _cheb_grid(n: int, pos: np.ndarray) -> np.ndarray:
    """Chebyshev distance of every cell to each position: (P, n, n)."""
    r = np.arange(n)
    dr = np.abs(r[None, :, None] - pos[:, 0, None, None])
    dc = np.abs(r[None, None, :] - pos[:, 1, None, None])
    return np.maximum(dr, dc)


def ansi(frame: Frame) -> str:
    """The grid as text, one character per cell separated by spaces, with a one-line header."""
    cfg, n = frame.config, frame.config.size
    d = _cheb_grid(n, frame.patrols).min(0)  # (n, n)
    grid = np.full((n, n), ".", dtype="<U1")
    grid[d < cfg.sight] = "+"
    grid[d <= cfg.shoot_range] = "*"
    for r, c in frame.items:
        grid[r, c] = "I"
    for r, c in frame.patrols:
        grid[r, c] = "P"
    grid[frame.agent[0], frame.agent[1]] = "A"
    ar, ac = (int(v) for v in frame.agent)
    i_d = int(np.abs(frame.items - frame.agent).max(-1).min())
    p_d = int(np.abs(frame.patrols - frame.agent).max(-1).min())
    seed = "" if frame.seed is None else f" instance={frame.seed}"
    head = (
        f"t={frame.t}{seed} agent=({ar},{ac}) item {'seen' if i_d < cfg.sight else 'unseen'} "
        f"(d={i_d}) patrol {'seen' if p_d < cfg.sight else 'unseen'} (d={p_d})"
    )
    return head + "\n" + "\n".join(" ".join(row) for row in grid) + "\n"


def _stamps(px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boolean (px, px) masks: disc (agent), square (patrol), diamond (item)."""
    c = (px - 1) / 2.0
    y, x = np.mgrid[0:px, 0:px]
    disc = (y - c) ** 2 + (x - c) ** 2 <= (0.42 * px) ** 2
    m = max(1, px // 6)
    square = np.zeros((px, px), dtype=bool)
    square[m : px - m, m : px - m] = True
    diamond = np.abs(y - c) + np.abs(x - c) <= 0.45 * px
    return disc, square, diamond


def _outline(img: np.ndarray, pos: np.ndarray, radius: int, px: int, col: np.ndarray) -> None:
    """Draw the 1-pixel border of the square of Chebyshev ``radius`` around ``pos`` (clipped)."""
    H, W = img.shape[:2]
    r0, r1 = (int(pos[0]) - radius) * px, (int(pos[0]) + radius + 1) * px - 1
    c0, c1 = (int(pos[1]) - radius) * px, (int(pos[1]) + radius + 1) * px - 1
    rs, re, cs, ce = max(r0, 0), min(r1, H - 1), max(c0, 0), min(c1, W - 1)
    for r in (r0, r1):
        if 0 <= r < H:
            img[r, cs : ce + 1] = col
    for c in (c0, c1):
        if 0 <= c < W:
            img[rs : re + 1, c] = col


def rgb(frame: Frame, cell_px: int | None = None) -> np.ndarray:
    """The grid as an ``(H, W, 3)`` uint8 image, ``H = W = size * cell_px`` (default ``max(4, 256 //
    size)``)."""
    cfg, n = frame.config, frame.config.size
    px = max(4, 256 // n) if cell_px is None else int(cell_px)
    if px < 2:
        raise ValueError(f"cell_px must be >= 2, got {cell_px}")
    color = np.broadcast_to(_BG, (n, n, 3)).copy()  # (n, n, 3) float
    a_sight = _cheb_grid(n, frame.agent.reshape(1, 2))[0] < cfg.sight
    p_d = _cheb_grid(n, frame.patrols).min(0)
    color[a_sight] = _AGENT_SIGHT
    both = a_sight & (p_d < cfg.sight)
    color[p_d < cfg.sight] = _PATROL_SIGHT
    color[both] = 0.5 * (_PATROL_SIGHT + _AGENT_SIGHT)
    color[p_d <= cfg.shoot_range] = _PATROL_SHOOT
    img = np.repeat(np.repeat(color.astype(np.uint8), px, 0), px, 1)  # (H, W, 3)
    if px >= 4:  # faint grid lines
        img[::px, :] = _GRID
        img[:, ::px] = _GRID
    for pos, col in [(p, _PATROL) for p in frame.patrols] + [(frame.agent, _AGENT)]:
        _outline(img, pos, cfg.sight - 1, px, col)  # sight border: Chebyshev radius sight - 1
    disc, square, diamond = _stamps(px)

    def stamp(pos: np.ndarray, mask: np.ndarray, col: np.ndarray) -> None:
        r, c = int(pos[0]) * px, int(pos[1]) * px
        img[r : r + px, c : c + px][mask] = col

    for p in frame.items:
        stamp(p, diamond, _ITEM)
    for p in frame.patrols:
        stamp(p, square, _PATROL)
    stamp(frame.agent, disc, _AGENT)
    return img


def render(frame: Frame, mode: str = "ansi") -> str | np.ndarray:
    """``ansi`` -> str, ``rgb_array`` -> (H, W, 3) uint8."""
    if mode == "ansi":
        return ansi(frame)
    if mode == "rgb_array":
        return rgb(frame)
    raise ValueError(f"render mode must be one of {list(RENDER_MODES)}, got {mode!r}")
