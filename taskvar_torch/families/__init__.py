"""The package's own task families, one folder each. Their contract and registry are
:mod:`taskvar_torch.contract` (docs/families.md), whose names are handed on here."""

from taskvar_torch.contract import (
    BUILTIN,
    ENTRY_POINT_GROUP,
    FAMILIES,
    HELDOUT_SEED,
    HELDOUT_SEEDS,
    HELDOUT_SIZE,
    Family,
    PatchLayout,
    TestDistribution,
    check_declaration,
    family,
    one_of,
    register_family,
    register_gym_ids,
    sealed_episode_seed,
)

__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "FAMILIES",
    "HELDOUT_SEED",
    "HELDOUT_SEEDS",
    "HELDOUT_SIZE",
    "Family",
    "PatchLayout",
    "TestDistribution",
    "check_declaration",
    "family",
    "one_of",
    "register_family",
    "register_gym_ids",
    "sealed_episode_seed",
]
