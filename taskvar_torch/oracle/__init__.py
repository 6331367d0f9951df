"""Exact values of small MDPs, for any family (docs/oracle.md): :mod:`.mdp` (the solver, policy
kernels, tie-snapping, quadrature), :mod:`.protocol` (what an oracle offers), :mod:`.tables` (tables
as heads), :mod:`.chains` (controllers as Markov chains, Algorithms 1-2) and :mod:`.episodes` (exact
returns per played episode).
"""

from __future__ import annotations

from taskvar_torch.oracle.chains import (
    CONTROLLER_NAMES,
    ControllerChains,
    discounted_chain_values,
)
from taskvar_torch.oracle.mdp import TIE_ATOL, gauss_legendre, greedy, snap_ties, solve_mdp
from taskvar_torch.oracle.protocol import ExactOracle, OracleTables
from taskvar_torch.oracle.tables import DerivedTables, TableLookup, table_heads

__all__ = [
    "CONTROLLER_NAMES",
    "TIE_ATOL",
    "ControllerChains",
    "DerivedTables",
    "ExactOracle",
    "OracleTables",
    "TableLookup",
    "discounted_chain_values",
    "gauss_legendre",
    "greedy",
    "snap_ties",
    "solve_mdp",
    "table_heads",
]
