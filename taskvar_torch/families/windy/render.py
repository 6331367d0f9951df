"""Rendering of the windy family: text (``ansi``) and an RGB image (``rgb_array``), numpy only."""

from __future__ import annotations

import numpy as np

from taskvar_torch.families.windy.dynamics import DIRECTIONS, WindyLayout

_ARROWS = {"north": "^", "south": "v", "east": ">", "west": "<"}
_COLOURS = {
    ".": (245, 245, 245),
    "S": (205, 225, 250),
    "W": (255, 236, 170),
    "#": (60, 60, 70),
    "G": (170, 225, 170),
}
CELL_PX = 32


def windy_ansi(
    layout: WindyLayout, cell: int | None, p: float | None, direction: str | None
) -> str:
    """Text grid: ``A`` agent, ``#`` wall, ``G`` goal, ``S`` start, windy cells as the wind arrow."""
    arrow = _ARROWS.get(direction or "", "W")
    lines = []
    for r, row in enumerate(layout.rows):
        chars = [arrow if ch == "W" else ch for ch in row]
        if cell is not None and cell // layout.width == r:
            chars[cell % layout.width] = "A"
        lines.append(" ".join(chars))
    head = "" if p is None else f"wind p={p:.2f} direction={direction}\n"
    return head + "\n".join(lines) + "\n"


def _triangle_mask(size: int, direction: str) -> np.ndarray:
    """Boolean (size, size) mask of an arrow head pointing ``direction``."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / (size - 1)
    # a triangle pointing north: apex at top centre, base near the bottom
    along, across = 1.0 - yy, np.abs(xx - 0.5)
    mask = (along > 0.2) & (along < 0.85) & (across < 0.38 * (0.85 - along) / 0.65)
    k = {"north": 0, "west": 1, "south": 2, "east": 3}[direction]
    return np.rot90(mask, k)


def windy_rgb(
    layout: WindyLayout, cell: int | None, direction: str | None, cell_px: int = CELL_PX
) -> np.ndarray:
    """``(H*px, W*px, 3)`` uint8 image: cells coloured by type, wind arrows, agent as a red disc."""
    H, W = layout.height, layout.width
    img = np.zeros((H * cell_px, W * cell_px, 3), dtype=np.uint8)
    arrow = _triangle_mask(cell_px, direction) if direction in DIRECTIONS else None
    yy, xx = np.mgrid[0:cell_px, 0:cell_px]
    c0 = (cell_px - 1) / 2
    disc = (yy - c0) ** 2 + (xx - c0) ** 2 <= (0.32 * cell_px) ** 2
    for r in range(H):
        for c in range(W):
            ch = layout.rows[r][c]
            tile = img[r * cell_px : (r + 1) * cell_px, c * cell_px : (c + 1) * cell_px]
            tile[:] = _COLOURS[ch]
            if ch == "W" and arrow is not None:
                tile[arrow] = (200, 120, 0)
            if cell is not None and r * W + c == cell:
                tile[disc] = (210, 30, 30)
            tile[0, :] = tile[:, 0] = (190, 190, 190)  # grid lines
    return img
