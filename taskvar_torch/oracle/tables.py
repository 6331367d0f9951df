"""Table-backed heads: a :class:`~taskvar_torch.heads.bundle.Heads` bundle from per-cell tables.

:func:`table_heads` lets controllers run on exact tables (the oracle's, or any hand-made ones)
exactly as on trained networks (docs/oracle.md; docs/design.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from taskvar_torch import keys
from taskvar_torch.heads.bundle import Heads

Tensor = torch.Tensor


class TableLookup(nn.Module):
    """A head backed by a table ``(S, ...)``: ``forward(cell) -> table[cell]`` (``one_hot``: the
    argmax of a one-hot observation).
    """

    def __init__(self, table: Tensor, one_hot: bool = False):
        super().__init__()
        self.register_buffer("table", table)
        self.one_hot = one_hot

    def forward(self, x: Tensor) -> Tensor:
        idx = x.argmax(-1) if self.one_hot else x  # (...,)
        return self.table[idx]  # (..., *table.shape[1:])


def table_heads(
    option_names: Sequence[str],
    *,
    averaging: Tensor | None = None,  # (S, A)
    options: Tensor | None = None,  # (S, O, A)
    switching: Tensor | None = None,  # (S, O)
    max_value: Tensor | None = None,  # (S, O)
    robustness: Tensor | None = None,  # (S, O, A)
    in_key: Any = keys.CELL,
    softmax_temperature: float | None = None,
) -> Heads:
    """A :class:`Heads` bundle whose heads gather rows of tables indexed by the cell.

    ``in_key`` is ``keys.CELL`` (integer cell) or ``keys.OBSERVATION`` (one-hot observation).
    """
    one_hot = in_key != keys.CELL

    def mod(table: Tensor | None, out_key: str) -> TensorDictModule | None:
        if table is None:
            return None
        return TensorDictModule(TableLookup(table, one_hot), in_keys=[in_key], out_keys=[out_key])

    return Heads(
        option_names,
        averaging=mod(averaging, keys.ACTION_VALUE),
        options=mod(options, keys.OPTION_ACTION_VALUE),
        switching=mod(switching, keys.OPTION_VALUE),
        max_value=mod(max_value, keys.MAX_VALUE),
        robustness=mod(robustness, keys.ROBUSTNESS),
        softmax_temperature=softmax_temperature,
    )


class DerivedTables:
    """What an exact oracle derives from its own tables (paper §3.3, Definition 1): ``V^{mu_bar}``,
    ``Q_hat``'s default instance set (cached) and the tables as heads; a mixin of the windy and Taxi
    oracles.
    """

    def v_mu_bar(self) -> Tensor:
        """``V^{mu_bar}(s) = sum_q mu_bar(s, q) Q_mu(s, q)`` ``(S,)`` (Definition 1's right-hand side)."""
        return (self.mu_bar() * self.switching_q()).sum(-1)

    def max_value(self, instances: Any = None) -> Tensor:
        """``Q_hat (S, O) = max_m Q^{m, mu_bar}(s, o)`` over ``instances`` (default: the training
        set), snapped to ``V^{mu_bar}(s)`` within a tie tolerance (Definition 1).
        """
        if instances is None:
            return self._max_value_default
        return self._max_value(*self.instance_set(instances))

    @cached_property
    def _max_value_default(self) -> Tensor:
        return self._max_value(*self.instance_set(None))

    def heads(
        self,
        in_key: Any = keys.CELL,
        dtype: torch.dtype = torch.float64,
        robustness: Tensor | None = None,
    ) -> Heads:
        """A :class:`Heads` bundle of the oracle's tables, read at ``in_key`` (a cell or a one-hot
        observation); ``robustness``: an optional ``(S, O, A)`` table.
        """
        t = dict(dtype=dtype, device=self.device)
        return table_heads(
            self.option_names,
            averaging=self.averaging_q().to(**t),
            options=self.option_q().permute(1, 0, 2).contiguous().to(**t),
            switching=self.switching_q().to(**t),
            max_value=self.max_value().to(**t),
            robustness=None if robustness is None else robustness.to(**t),
            in_key=in_key,
            softmax_temperature=self.mu_temperature,
        )
