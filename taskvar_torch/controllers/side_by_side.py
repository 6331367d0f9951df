"""Several controllers side by side on consecutive slices of one batched env, as the Wargus Figure 4
protocol tests them (paper §3.5.3; docs/wargus-fig4.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from taskvar_torch import keys
from taskvar_torch.controllers.base import Controller, option_first, select0
from taskvar_torch.controllers.hierarchy import HierarchyController
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.heads.snapshots import HeadValues


class SideBySide(TensorDictModuleBase):
    """Several controllers on consecutive equal slices of one batch: one env step serves them all.

    Slice ``i`` (rows ``[i k, (i + 1) k)``) is driven by ``controllers[i]``; every head they need
    runs once over the whole batch (:class:`HeadValues`). Traces a controller does not write are -1
    (``option``, ``hierarchy_level``) or False (``interrupted``).
    """

    TRACES = ((keys.OPTION, -1), (keys.HIERARCHY_LEVEL, -1), (keys.INTERRUPTED, False))

    def __init__(self, controllers: Sequence[Controller], slice_size: int):
        super().__init__()
        heads = {id(c.heads) for c in controllers}
        if len(heads) != 1:
            raise ValueError("SideBySide needs controllers over one shared Heads bundle")
        self.controllers = torch.nn.ModuleList(controllers)
        self.heads = controllers[0].heads
        self.subtasks = next((c.subtasks for c in controllers if c.subtasks is not None), None)
        self.k = int(slice_size)
        names = [h for h in self.heads.heads if any(h in c.required_heads for c in controllers)]
        self.head_names = names
        self.head_values = (
            HeadValues(self.heads, names) if HeadValues.supports(self.heads, names) else None
        )
        self.in_keys = [*self.heads.in_keys, keys.RUNNING_OPTION]
        self.out_keys = [
            keys.ACTION,
            (keys.NEXT, keys.RUNNING_OPTION),
            *(k for k, _ in self.TRACES),
        ]

    @property
    def batchable(self) -> bool:
        """Whether groups of frozen heads can be decided side by side: stacked heads and no
        random draws (a softmax mu_bar draws from the controllers' generators per row)."""
        return (
            self.head_values is not None
            and self.head_values.stack is not None
            and self.heads.softmax_temperature is None
        )

    def decide_batch(
        self,
        td: Any,
        running: torch.Tensor,
        params: Sequence[torch.Tensor] | None = None,
        thresholds: Mapping[str, torch.Tensor] | None = None,
    ) -> dict[str, torch.Tensor]:
        """Decisions ``(B,)`` at ``td`` with carried ``running (B,)``: ``action``, ``next_running``,
        traces.

        ``params``: :meth:`HeadValues.snapshot` s stacked over ``G`` groups of rows (``None``: live
        heads); ``thresholds``: the hierarchy's per-row thresholds (:meth:`threshold_rows`).
        """
        k, M = self.k, len(self.controllers)
        G = 1 if params is None else params[0].shape[0]
        if self.head_values is not None:
            values_all = self.head_values(td.get(keys.OBSERVATION), params)
        else:  # generic heads (e.g. tables reading other keys): the bundle's tensordict path
            if params is not None:
                raise ValueError("decide_batch with params needs stacked heads (see batchable)")
            td = self.heads(td)
            values_all = {HEAD_OUT_KEYS[h]: td.get(HEAD_OUT_KEYS[h]) for h in self.head_names}
        beta = None
        if self.subtasks is not None:
            beta = self.subtasks.termination(td)  # (B, O)

        def part(x: torch.Tensor, i: int) -> torch.Tensor:  # rows of controller i, all groups
            return x.view(G, M, k, *x.shape[1:])[:, i].reshape(G * k, *x.shape[1:])

        outs = []
        for i, c in enumerate(self.controllers):
            values = {
                HEAD_OUT_KEYS[h]: part(values_all[HEAD_OUT_KEYS[h]], i) for h in c.required_heads
            }
            values.update({key: part(v, i) for key, v in c.extra_inputs(td).items()})
            if thresholds and isinstance(c, HierarchyController):
                values.update(thresholds)  # per-row (G k, O)
            run = part(running, i) if c.stateful else None
            term = None
            if run is not None and c.subtasks is not None:
                term = select0(option_first(part(beta, i)), run.clamp(min=0))  # beta_{o_run}(s_t)
            out = c.decide(values, run, term)
            if not c.stateful:
                out["option"] = torch.full_like(out["action"], -1)
            outs.append(out)

        def whole(parts: list[torch.Tensor]) -> torch.Tensor:  # back to rows (g, i, j)
            return torch.stack([p.view(G, k) for p in parts], 1).reshape(G * M * k)

        result = {
            keys.ACTION: whole([o["action"] for o in outs]),
            "next_running": whole([o["option"] for o in outs]),
        }
        for key, fill in self.TRACES:
            result[key] = whole(
                [
                    o[key] if key in c.trace_keys else _full(o["action"], fill)
                    for o, c in zip(outs, self.controllers)
                ]
            )
        return result

    def threshold_rows(
        self, calibrations: Sequence[RobustnessCalibration | None]
    ) -> dict[str, torch.Tensor]:
        """The hierarchy's per-row thresholds and scales ``(G k, O)`` for one calibration per group
        (empty when some group has none).
        """
        c = next((c for c in self.controllers if isinstance(c, HierarchyController)), None)
        if c is None:
            return {}
        cals = [cal or c.calibration for cal in calibrations]
        if any(cal is None for cal in cals):
            return {}
        return {
            keys.ROBUSTNESS_TAU: _rows([cal.tau for cal in cals], self.k),
            keys.ROBUSTNESS_SCALE: _rows([cal.scale for cal in cals], self.k),
        }

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        out = self.decide_batch(td, td.get(keys.RUNNING_OPTION))
        td.set(keys.ACTION, out[keys.ACTION])
        td.set((keys.NEXT, keys.RUNNING_OPTION), out["next_running"])
        for key, _ in self.TRACES:
            td.set(key, out[key])
        return td


def _rows(per_group: Sequence[torch.Tensor], k: int) -> torch.Tensor:
    """``(G k, O)``: each group's ``(O,)`` vector repeated for its ``k`` rows."""
    return torch.stack(per_group).repeat_interleave(k, 0)


def _full(like: torch.Tensor, value: int | bool) -> torch.Tensor:
    """A tensor of ``like``'s shape and device filled with ``value`` (bool or int64)."""
    dtype = torch.bool if isinstance(value, bool) else torch.int64
    return torch.full(like.shape, value, dtype=dtype, device=like.device)


__all__ = ["SideBySide"]
