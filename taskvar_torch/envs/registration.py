"""Gymnasium registration of every family's ids (``Family.gym_ids``) on ``import taskvar_torch``;
under the ``taskvar`` command an installed family's ids are registered when the command asks for it,
so a broken plugin cannot break other commands.
"""

from __future__ import annotations


def register_envs() -> None:
    """Register the Gymnasium ids of every registered family (idempotent); each installed
    family's entry point is imported, a broken one is a warning naming it."""
    from taskvar_torch.contract import FAMILIES, register_gym_ids

    for fam in FAMILIES.values():
        register_gym_ids(fam)


def register_builtin_envs() -> None:
    """Register the Gymnasium ids of the built-in families and of those already imported."""
    from taskvar_torch.contract import FAMILIES, register_gym_ids

    for fam in FAMILIES.loaded().values():
        register_gym_ids(fam)


def env_ids() -> dict[str, tuple[str, dict]]:
    """Every registered family's Gymnasium ids: id -> ``(entry point, kwargs)``."""
    from taskvar_torch.contract import FAMILIES

    return {i: spec for fam in FAMILIES.values() for i, spec in fam.gym_ids.items()}
