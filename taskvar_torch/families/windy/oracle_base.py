"""What both windy oracles (:class:`.oracle.WindyOracle`, :class:`.sparse_oracle.SparseWindyOracle`)
share: the model, horizon, training distribution, Q_hat's ``p`` grid, the instance set and the
quadrature (paper §3.1-3.3; docs/oracle.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.env import resolve_layout
from taskvar_torch.families.windy.instances import WindyInstances, windy_instances
from taskvar_torch.oracle.mdp import gauss_legendre

Tensor = torch.Tensor


def layout_of(model_or_layout: windy.WindyModel | windy.WindyLayout | str) -> windy.WindyLayout:
    """The layout of a model, a layout, a layout name or a map string (both oracles' input)."""
    if isinstance(model_or_layout, windy.WindyModel):
        return model_or_layout.layout
    return resolve_layout(model_or_layout)


def p_grid_values(p_grid: int | Sequence[float], instances: WindyInstances) -> Tensor:
    """Q_hat's ``p`` values (float64): ``p_grid`` evenly spaced over ``instances``' range (an
    int) or the given values; a one-line ``ValueError`` otherwise."""
    if isinstance(p_grid, int):
        if p_grid < 1:
            raise ValueError(f"p_grid must be >= 1 or a sequence of p values, got {p_grid}")
        return torch.linspace(instances.p_low, instances.p_high, p_grid, dtype=torch.float64)
    grid = torch.as_tensor(list(p_grid), dtype=torch.float64)
    if grid.numel() == 0 or bool(((grid < 0) | (grid > 1)).any()):
        raise ValueError(f"p_grid values must be in [0, 1], got {list(p_grid)}")
    return grid


class WindyOracleBase:
    """A windy layout's model and instances for an exact oracle.

    Args:
        model_or_layout: a ``WindyModel``, a layout, a layout name or a map string.
        gamma: discount of the values, in [0, 1). horizon: episode length of the returns.
        train_instances: the training distribution (name, dict or :class:`WindyInstances`).
        p_grid: ``p`` values of Q_hat's instance set (an int: evenly spaced).
        quad_nodes: Gauss-Legendre nodes in ``p`` (``None``: ``ceil(horizon / 2)``, exact).
        device: torch device of the tables.
    """

    instance_keys = ("p", "direction")
    """The ``("instance", key)`` fields an instance is given by, in order (docs/families.md)."""

    def __init__(
        self,
        model_or_layout: windy.WindyModel | windy.WindyLayout | str,
        gamma: float,
        horizon: int | None,
        train_instances: str | dict | WindyInstances,
        p_grid: int | Sequence[float],
        quad_nodes: int | None,
        device: torch.device | str,
    ):
        layout = layout_of(model_or_layout)
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {gamma}")
        self.layout = layout
        self.device = torch.device(device)
        self.model = windy.WindyModel(layout, self.device)
        self.gamma = float(gamma)
        self.horizon = int(horizon) if horizon is not None else windy.default_horizon(layout)
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.train_instances = windy_instances(train_instances)
        if quad_nodes is None:  # exact for returns: a polynomial of degree < horizon in p
            quad_nodes = max(1, math.ceil(self.horizon / 2))
        if quad_nodes < 1:
            raise ValueError(f"quad_nodes must be >= 1, got {quad_nodes}")
        self.quad_nodes = int(quad_nodes)
        self.p_grid = p_grid_values(p_grid, self.train_instances).to(self.device)
        self.S, self.A = self.model.num_cells, self.model.num_actions
        self.start_cells = self.model.start_cells  # (K,)
        self.is_goal = self.model.is_goal  # (S,)

    def _f(self, x: Any) -> Tensor:
        return torch.as_tensor(x, dtype=torch.float64, device=self.device)

    def _instances_arg(self, p: Any, direction: Any) -> tuple[Tensor, Tensor, bool]:
        """``(p (B,), direction (B,), scalar)`` from scalars, sequences or tensors (broadcast)."""
        scalar = not isinstance(p, (Sequence, Tensor, np.ndarray)) or (
            isinstance(p, (Tensor, np.ndarray)) and np.ndim(p) == 0
        )
        if isinstance(direction, str) or not isinstance(direction, (Sequence, Tensor, np.ndarray)):
            d = torch.tensor([windy.direction_index(direction)], device=self.device)
        elif isinstance(direction, Tensor):
            d = direction.to(self.device, torch.int64).reshape(-1)
        else:
            d = torch.tensor([windy.direction_index(x) for x in direction], device=self.device)
            scalar = False
        pt = self._f(p).reshape(-1)
        if bool(((pt < 0) | (pt > 1)).any()):
            raise ValueError(f"p must be in [0, 1], got {p}")
        if bool(((d < 0) | (d >= len(windy.DIRECTIONS))).any()):
            raise ValueError(f"direction must be one of {list(windy.DIRECTIONS)} or 0..3")
        pt, d = torch.broadcast_tensors(pt, d)
        return pt.contiguous(), d.contiguous(), scalar and pt.numel() == 1

    def instance_set(self, instances: Any = None) -> tuple[Tensor, Tensor]:
        """``(p (M,), direction (M,))`` of a finite instance set (Q_hat's max, Definition 1):
        ``None`` (the training one), a :class:`WindyInstances` (or name/dict), or a ``(p,
        direction)`` pair."""
        if isinstance(instances, tuple) and len(instances) == 2:
            pt, d, _ = self._instances_arg(instances[0], instances[1])
            return pt, d
        dist = self.train_instances if instances is None else windy_instances(instances)
        if dist.points is not None:
            return self._instances_arg([p for p, _ in dist.points], [d for _, d in dist.points])[:2]
        t = self.p_grid
        if instances is not None:
            ti = self.train_instances
            span = ti.p_high - ti.p_low
            u = (t - ti.p_low) / span if span > 0 else torch.zeros_like(t)
            t = dist.p_low + (dist.p_high - dist.p_low) * u
        dirs = [windy.direction_index(x) for x in dist.directions]
        pp = t.repeat(len(dirs))
        dd = torch.tensor(dirs, device=self.device).repeat_interleave(t.numel())
        return pp, dd

    def quadrature(self, instances: Any = None) -> tuple[Tensor, Tensor, Tensor]:
        """``(p (K,), direction (K,), weight (K,))`` integrating over an instance distribution
        (Gauss-Legendre in ``p``, or each of ``points`` equally).
        """
        dist = self.train_instances if instances is None else windy_instances(instances)
        if dist.points is not None:
            pt, d = self.instance_set(dist)
            return pt, d, torch.full_like(pt, 1.0 / pt.numel())
        x, w = gauss_legendre(self.quad_nodes, dist.p_low, dist.p_high)
        dirs = [windy.direction_index(x) for x in dist.directions]
        nd = len(dirs)
        pp = x.to(self.device).repeat(nd)
        dd = torch.tensor(dirs, device=self.device).repeat_interleave(x.numel())
        ww = (w.to(self.device) / nd).repeat(nd)
        return pp, dd, ww
