"""Exact values of small MDPs, for any family (docs/oracle.md).

- :mod:`~taskvar_torch.oracle.mdp`: the generic MDP solver (value iteration with a
  policy-iteration polish), policy kernels, tie-snapping, Gauss-Legendre quadrature;
- :mod:`~taskvar_torch.oracle.protocol`: the oracle protocol (:class:`OracleTables`,
  :class:`ExactOracle`) the windy and Taxi oracles implement;
- :mod:`~taskvar_torch.oracle.tables`: table -> head adapters (:func:`table_heads`) and the
  tables an oracle derives from its own (:class:`DerivedTables`);
- :mod:`~taskvar_torch.oracle.chains`: controllers as Markov chains (Algorithms 1-2), exact
  returns, firing counts and discounted chain values, mixed into each family's oracle
  (:class:`~taskvar_torch.families.windy.oracle.WindyOracle`,
  :class:`~taskvar_torch.families.taxi.oracle.TaxiOracle`).
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
