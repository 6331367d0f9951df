"""Controller settings: the ``train.*`` keys a controller reads from trained heads, changeable at
evaluation without retraining (docs/evaluation.md); changing one there changes the controller
only, on heads trained for the bundle's values.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, TypeVar

from taskvar_torch.config.loader import apply_overrides

T = TypeVar("T")

CONTROLLER_KEYS = (
    "train.robustness_threshold",
    "train.robustness_tau",
    "train.robustness_keep_share",
    "train.hierarchy_root_policy",
    "train.hierarchy_termination",
    "train.hierarchy_descent",
    "train.mu_bar",
    "train.mu_bar_temperature",
)
"""The config keys an evaluation may override (each documented in ``taskvar train --help-all``)."""


def check_controller_overrides(items: Sequence[str]) -> list[str]:
    """``items`` (``key=value``) as a list, or a one-line ``ValueError`` naming the first one that
    is malformed or not a controller setting, and the allowed keys."""
    out = []
    for item in items:
        key, eq, _ = str(item).partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(
                f"expected a controller setting key=value, got {item!r} (a bundle is given as "
                "--checkpoint PATH)"
            )
        if key not in CONTROLLER_KEYS:
            hint = (
                " (an env key changes the test distribution: --shift KEY=V)"
                if key.startswith("env.")
                else ""
            )
            raise ValueError(
                f"{key!r} is not a controller setting{hint}; an evaluation may change only "
                f"{', '.join(CONTROLLER_KEYS)} (anything else needs retraining)"
            )
        out.append(f"{key}={item.partition('=')[2]}")
    return out


def with_controller_settings(cfg: T, items: Sequence[str]) -> T:
    """``cfg`` with the controller settings ``items`` (``key=value``) applied: keys checked by
    :func:`check_controller_overrides`, values validated like any config override."""
    items = check_controller_overrides(items)
    return apply_overrides(cfg, items) if items else cfg


def controller_settings(cfg: Any) -> dict[str, Any]:
    """The value of every :data:`CONTROLLER_KEYS` key in ``cfg`` (what ``metrics.json`` records
    as ``controller``)."""
    return {k: getattr(cfg.train, k.split(".", 1)[1]) for k in CONTROLLER_KEYS}


__all__ = [
    "CONTROLLER_KEYS",
    "check_controller_overrides",
    "controller_settings",
    "with_controller_settings",
]
