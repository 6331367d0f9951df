"""The flat averaging controller (paper §3.1): greedy in ``Q_avg``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from taskvar_torch import keys
from taskvar_torch.controllers.base import Controller, argmax0, first_argmax

Tensor = torch.Tensor


class AveragingController(Controller):
    """Greedy in the averaging head (paper §3.1): the flat baseline; carries no state."""

    name = "averaging"
    required_heads = ("averaging",)
    stateful = False

    def decide_of(
        self, values: Mapping[str, Tensor], running: Tensor | None, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        return {"action": argmax0(values[keys.ACTION_VALUE])}  # (A, B) -> (B,)

    def decide_scalar(
        self, values: Mapping[str, list], running: int, terminated: bool
    ) -> dict[str, Any]:
        return {"action": first_argmax(values[keys.ACTION_VALUE])}
