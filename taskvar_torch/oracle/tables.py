"""Table-backed heads: a :class:`~taskvar_torch.heads.bundle.Heads` bundle from per-cell tables.

:func:`table_heads` lets controllers run on exact tables (the oracle's, or any hand-made ones)
exactly as on trained networks (docs/oracle.md; docs/design.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from taskvar_torch import keys
from taskvar_torch.heads.bundle import Heads

Tensor = torch.Tensor


class TableLookup(nn.Module):
    """A head backed by a table: ``forward(cell) -> table[cell]`` (or argmax of a one-hot observation).

    Args:
        table: ``(S, ...)`` values per cell.
        one_hot: read a one-hot observation ``(..., S)`` instead of an integer cell.
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
