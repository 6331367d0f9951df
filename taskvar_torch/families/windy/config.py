"""The windy family's own config keys: ``env.windy.*`` (docs/windy-fig2.md, docs/scale.md) and
its Figure 2 experiment's, ``experiment.*`` (:class:`Fig2Config`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from taskvar_torch import rng

MAX_HORIZON = rng.RESET_COUNTER - 1
"""Largest ``env.windy.horizon``: step ``t`` draws from counters below ``rng.RESET_COUNTER``."""
MAX_COUNT = 2**31 - 1
"""Largest ``experiment.episodes_per_run`` (the config's counts' bound, config/validate.py)."""


@dataclass(frozen=True)
class WindyConfig:
    """The windy family's own env keys (``env.windy.*``); range-checked on construction, the
    layout itself by the family's validation (``family.py``)."""

    layout: str = "default"
    """Windy layout: a name (default, middle_exits, whole_column_windy), a multi-line map string,
    or 'generated' to build it from height/width/num_exits/wall_col/wind_cells_per_exit."""
    height: int | None = None
    """Generated windy grid: number of rows (only with layout='generated')."""
    width: int | None = None
    """Generated windy grid: number of columns (only with layout='generated')."""
    num_exits: int | None = None
    """Generated windy grid: exits in the wall, >= 2 (only with layout='generated'; default 2)."""
    wall_col: int | None = None
    """Generated windy grid: column of the wall (only with layout='generated'; default width // 2)."""
    wind_cells_per_exit: int | None = None
    """Generated windy grid: windy cells west of each exit (only with layout='generated'; default 1)."""
    horizon: int | None = None
    """Steps before truncation; null: max(100, 4 * (height + width))."""
    obs_encoding: str = "onehot"
    """Observation: onehot (one-hot cell), coords_patch (coordinates + local patch),
    fourier_patch (coords_patch + sin/cos features of the coordinates) or rowcol_patch
    (coords_patch + one-hot row and column)."""
    patch_radius: int = 2
    """coords_patch encodings: radius r of the (2r+1)^2 local patch."""

    def __post_init__(self) -> None:
        if self.horizon is not None and not (
            isinstance(self.horizon, int) and 1 <= self.horizon <= MAX_HORIZON
        ):
            raise ValueError(f"horizon must be in [1, {MAX_HORIZON}], got {self.horizon}")
        if not (isinstance(self.patch_radius, int) and 0 <= self.patch_radius <= 4096):
            raise ValueError(f"patch_radius must be in [0, 4096], got {self.patch_radius}")


@dataclass(frozen=True)
class Fig2Config:
    """Figure 2's own keys, read flat under ``experiment.*`` in a windy config beside the shared
    ``experiment.runs`` (the test runs) and ``experiment.quick_overrides``."""

    episodes_per_run: int = 10_000
    """Windy Figure 2: test episodes per run."""

    def __post_init__(self) -> None:
        v = self.episodes_per_run
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_COUNT:
            raise ValueError(f"episodes_per_run must be in [1, {MAX_COUNT}], got {v}")


KEYS = tuple(WindyConfig.__dataclass_fields__)
"""The windy keys, which configs written before ``env.windy`` held at ``env.*``."""


def section(cfg: Any) -> WindyConfig:
    """The config's windy keys (``env.windy``; defaults where it was built without them)."""
    return getattr(cfg.env, "windy", None) or WindyConfig()


__all__ = ["KEYS", "MAX_HORIZON", "Fig2Config", "WindyConfig", "section"]
