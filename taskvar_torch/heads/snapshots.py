"""Batched inference of every head over ``G`` frozen head snapshots in one pass.

The Wargus Figure 4 protocol (paper §3.5.3; docs/wargus-fig4.md) tests each trial's heads as
they were at the end of that trial's learning phase. Rather than testing every trial on its own,
the experiment keeps a frozen copy of the heads per trial (:meth:`HeadValues.snapshot`) and tests
``G`` trials side by side: rows ``[g R, (g + 1) R)`` of one batch of observations run through
snapshot ``g`` (:meth:`HeadValues.__call__` with the snapshots stacked). Every head comes from one
batched pass of the heads' shared :class:`~taskvar_torch.heads.networks.StackedMLP`
(:meth:`StackedMLP.forward_snapshots`).

The pass is an explicit ``baddbmm`` per layer over the ``G K`` (snapshot, member) pairs
(:meth:`StackedMLP.forward_snapshots`): member ``(g, k)`` is one batch entry of the op the
learner's fused pass (:meth:`StackedMLP.forward`) runs for member ``k``. With the Wargus shapes a
snapshot's values are bit-equal to each head run on its own
(``tests/families/wargus/test_wargus_fast_loop.py``).

Examples:
    >>> values = HeadValues(heads, ["averaging", "options"])  # doctest: +SKIP
    >>> snaps = [values.snapshot() for _ in range(G)]  # one per trial, taken as it ends
    >>> params = [torch.stack(p) for p in zip(*snaps)]  # stacked along a new first dim G
    >>> values(obs, params)  # obs (G R, D) -> {out_key: (G R, *out_shape)}
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

    When the heads are members of one :class:`StackedMLP` (how the trainer builds them), every head
    comes from *one* batched pass of the stack (the learner's fused pass), and the pass can run
    ``G`` frozen copies of the weights (:meth:`snapshot`) at once, rows ``[g R, (g + 1) R)`` through
    copy ``g``: the experiment tests many trials' heads in one batch. An optimism-gap head combines
    its members' outputs. Equal to running each head on its own (each member's slice is computed
    by the same matmul; checked in the tests).

    Args:
        heads: the bundle.
        names: the heads to compute (names in ``heads.heads``); keys of the result are their
            out-keys (:data:`~taskvar_torch.heads.bundle.HEAD_OUT_KEYS`).

    Attributes:
        nets: ``{out_key: network}``, the plain network inside each head.
        stack: the one :class:`StackedMLP` every head is made of, or ``None`` (independent
            networks: each head runs on its own, and there are no snapshots).
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
        """A frozen copy of the stack's weights and biases (for :meth:`__call__`'s ``params``):
        :meth:`StackedMLP.snapshot`, ``[weight_0, ..., bias_0, ...]`` of shapes ``(K, d_in,
        d_out)`` and ``(K, 1, d_out)``."""
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
