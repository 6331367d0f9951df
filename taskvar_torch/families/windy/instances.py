"""Windy instance distributions (paper §2.2): frozen data, sampled from per-episode keys
(``rng.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from taskvar_torch import rng
from taskvar_torch.families.windy.dynamics import DIRECTIONS, direction_index

# reset-time counters (see rng.RESET_COUNTER)
_C_P, _C_DIR, _C_POINT = rng.RESET_COUNTER + 1, rng.RESET_COUNTER + 2, rng.RESET_COUNTER + 3


@dataclass(frozen=True)
class WindyInstances:
    """Distribution of windy instances ``(p, direction)``: ``p ~ U[p_low, p_high]``, direction
    uniform over ``directions``, or uniform over ``points``. Named: ``train``, ``test``, ``south``,
    ``north``."""

    p_low: float = 0.0
    p_high: float = 1.0
    directions: tuple[str, ...] = ("north", "south")
    points: tuple[tuple[float, str], ...] | None = None

    NAMES = ("train", "test", "south", "north")

    def __post_init__(self):
        for name, v in (("p_low", self.p_low), ("p_high", self.p_high)):
            if not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.p_low > self.p_high:
            raise ValueError(f"p_low ({self.p_low}) must be <= p_high ({self.p_high})")
        if not self.directions:
            raise ValueError(f"directions must name at least one of {list(DIRECTIONS)}")
        object.__setattr__(self, "directions", tuple(self.directions))
        for d in self.directions:
            direction_index(d)
        if self.points is not None:
            pts = tuple((float(p), str(d)) for p, d in self.points)
            if not pts:
                raise ValueError("points must hold at least one (p, direction) pair")
            for p, d in pts:
                if not 0.0 <= p <= 1.0:
                    raise ValueError(f"p must be in [0, 1], got {p}")
                direction_index(d)
            object.__setattr__(self, "points", pts)
        object.__setattr__(self, "_tensors", {})  # device -> constant tensors (not a field)

    @classmethod
    def named(cls, name: str) -> WindyInstances:
        """``train``, ``test``, ``south`` or ``north``."""
        if name in ("train", "test"):
            return cls()
        if name in ("south", "north"):
            return cls(directions=(name,))
        raise ValueError(f"instance distribution must be one of {list(cls.NAMES)}, got {name!r}")

    @classmethod
    def fixed(cls, p: float, direction: str | int) -> WindyInstances:
        """A single instance."""
        return cls(points=((float(p), DIRECTIONS[direction_index(direction)]),))

    @property
    def counters(self) -> tuple[int, ...]:
        """The reset counters :meth:`sample` draws from (one per random quantity)."""
        return (_C_POINT,) if self.points is not None else (_C_P, _C_DIR)

    def sample(self, key: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(p, direction)`` for each episode key in ``key`` (B,) int64."""
        counters = torch.tensor(self.counters, device=key.device).unsqueeze(-1)  # (C, 1)
        return self.from_bits(rng.draw_bits(key, counters))

    def from_bits(self, bits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`sample` from ``rng.draw_bits(key, c)`` for the ``c`` in :attr:`counters`
        (``(C, B)``), so a caller can draw them together with its own counters."""
        values = self._tensors.get(bits.device)
        if values is None:
            values = self._tensors[bits.device] = _values(self, bits.device)
        if self.points is not None:
            ps, ds = values
            k = rng.index_of(bits[0], len(self.points))
            return ps.index_select(0, k), ds.index_select(0, k)
        u = rng.uniform_of(bits[0])
        p = self.p_low + (self.p_high - self.p_low) * u
        (dirs,) = values
        return p, dirs.index_select(0, rng.index_of(bits[1], len(dirs)))


def _values(instances: WindyInstances, device: torch.device) -> tuple[torch.Tensor, ...]:
    """The distribution's constant tensors on ``device``: point ``p`` and direction values, or the
    direction indices (built once, not at every reset)."""
    if instances.points is not None:
        ps = torch.tensor([p for p, _ in instances.points], dtype=torch.float32, device=device)
        ds = [direction_index(d) for _, d in instances.points]
        return ps, torch.tensor(ds, dtype=torch.int64, device=device)
    dirs = [direction_index(d) for d in instances.directions]
    return (torch.tensor(dirs, dtype=torch.int64, device=device),)


def windy_instances(spec: str | WindyInstances | dict) -> WindyInstances:
    """Coerce a name, a dict of fields, or a :class:`WindyInstances` into one."""
    if isinstance(spec, WindyInstances):
        return spec
    if isinstance(spec, str):
        return WindyInstances.named(spec)
    if isinstance(spec, dict):
        allowed = {"p_low", "p_high", "directions", "points"}
        unknown = sorted(set(spec) - allowed)
        if unknown:
            raise ValueError(f"unknown instance field(s) {unknown}; allowed: {sorted(allowed)}")
        return WindyInstances(**spec)
    raise ValueError(
        f"instances must be a name {list(WindyInstances.NAMES)}, a dict or WindyInstances"
    )
