"""The Taxi family: Gymnasium's Taxi-v4 as a family of MDPs (docs/taxi.md): its dynamics, env,
Gymnasium wrapper, MAXQ options and exact oracle, in one package (docs/families.md).

Modules: :mod:`.dynamics` (pure batched transitions, instances), :mod:`.env`, :mod:`.gym_env`,
:mod:`.subtasks`, :mod:`.oracle` (:class:`~taskvar_torch.families.taxi.oracle.TaxiOracle`) and
:mod:`.family` (the declaration, the ``taxi`` entry point).
"""

from taskvar_torch.families.taxi.dynamics import TaxiInstances, TaxiModel
from taskvar_torch.families.taxi.env import TaxiEnv

__all__ = ["TaxiEnv", "TaxiInstances", "TaxiModel"]
