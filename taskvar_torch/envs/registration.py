"""Gymnasium registration of every family's ids (``Family.gym_ids``), done on ``import
taskvar_torch``: the built-in families' ``taskvar/`` ids and those of installed families alike."""

from __future__ import annotations


def register_envs() -> None:
    """Register the Gymnasium ids of every registered family (idempotent)."""
    from taskvar_torch.families import FAMILIES, register_gym_ids

    for name in FAMILIES:
        register_gym_ids(FAMILIES[name])


def env_ids() -> dict[str, tuple[str, dict]]:
    """Every registered family's Gymnasium ids: id -> ``(entry point, kwargs)``."""
    from taskvar_torch.families import FAMILIES

    return {i: spec for name in FAMILIES for i, spec in FAMILIES[name].gym_ids.items()}
