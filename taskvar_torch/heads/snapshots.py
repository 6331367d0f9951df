"""Batched inference of every head over ``G`` frozen head snapshots in one pass, so the Wargus
Figure 4 protocol tests ``G`` trials' heads side by side (paper §3.5.3; docs/wargus-fig4.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from taskvar_torch import keys
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS, Heads
from taskvar_torch.heads.max_value import OptimismGapHead
from taskvar_torch.heads.networks import StackedHead, StackedMLP, head_network


class HeadValues:
    """Head outputs ``{out_key: (B, ...)}`` from plain observations ``(B, D)`` (inference).

    When the heads are members of one :class:`StackedMLP`, every head comes from one batched pass,
    optionally of ``G`` frozen weight copies (:meth:`snapshot`), rows ``[g R, (g + 1) R)`` through
    copy ``g``; equal to running each head on its own (tested).

    Args:
        heads: the bundle.
        names: the heads to compute; the result's keys are their out-keys.
    """

    def __init__(self, heads: Heads, names: Sequence[str]):
        self.nets = {HEAD_OUT_KEYS[n]: head_network(heads.heads[n]) for n in names}
        members = [m for net in self.nets.values() for m in _members(net)]
        stacks = {id(m.stack): m.stack for m in members if isinstance(m, StackedHead)}
        fused = len(stacks) == 1 and all(isinstance(m, StackedHead) for m in members)
        self.stack: StackedMLP | None = next(iter(stacks.values())) if fused else None
        # the members the heads read: one pass runs these only (the behaviour policy's heads are
        # members 0-4 of the Wargus stack's 7)
        self.members: tuple[int, int] | None = None
        if fused:
            self.members = (
                min(m.index for m in members),
                max(m.index + m.members for m in members),
            )

    @staticmethod
    def supports(heads: Heads, names: Sequence[str]) -> bool:
        """Whether every head reads the observation only (``TensorDictModule`` with one out-key)."""
        return all(
            list(getattr(heads.heads[n], "in_keys", ())) == [keys.OBSERVATION]
            and len(getattr(heads.heads[n], "out_keys", ())) == 1
            for n in names
        )

    def snapshot(self) -> list[torch.Tensor]:
        """A frozen copy of the stack's weights and biases for :meth:`__call__`'s ``params``."""
        if self.stack is None:
            raise ValueError("snapshots need heads stored in one StackedMLP")
        return self.stack.snapshot()

    def __call__(
        self, obs: torch.Tensor, params: Sequence[torch.Tensor] | None = None
    ) -> dict[str, torch.Tensor]:
        """Every head on ``obs`` ``(B, D)``; ``params``: :meth:`snapshot` s stacked along a new
        first dim ``G`` (rows split into ``G`` equal groups), ``None``: the live weights."""
        if self.stack is None:  # independent networks: each head on its own
            if params is not None:
                raise ValueError("snapshots need heads stored in one StackedMLP")
            return {k: net(obs) for k, net in self.nets.items()}
        out = self.stack.forward_snapshots(obs, params, self.members)  # (G, K', B / G, max_out)

        def run(net: torch.nn.Module) -> torch.Tensor:  # (G, B / G, flat output)
            if isinstance(net, OptimismGapHead):
                return net.combine(run(net.base), run(net.gap))
            return net.select(out, dim=1, first=self.members[0])

        # elementwise math (the optimism gap's softplus) runs on rows of the layout forward_one
        # gives (same kernel path, same bits); only the final values are reshaped
        return {k: run(net).reshape(obs.shape[0], *_out_shape(net)) for k, net in self.nets.items()}


def _out_shape(net: torch.nn.Module) -> tuple[int, ...]:
    """A stacked head's output shape per row (an optimism-gap head: its base's)."""
    return _out_shape(net.base) if isinstance(net, OptimismGapHead) else net.out_shape


def _members(net: torch.nn.Module) -> list[torch.nn.Module]:
    """The networks a head is made of (an optimism-gap head is its base and its gap)."""
    if isinstance(net, OptimismGapHead):
        return _members(net.base) + _members(net.gap)
    return [net]


__all__ = ["HeadValues"]
