"""The Taxi family: Gymnasium's Taxi-v4 as a family of MDPs (docs/taxi.md); :mod:`.family` is the
declaration (the ``taxi`` entry point).
"""

from taskvar_torch.families.taxi.dynamics import TaxiInstances, TaxiModel
from taskvar_torch.families.taxi.env import TaxiEnv

__all__ = ["TaxiEnv", "TaxiInstances", "TaxiModel"]
