"""MDP families: pure batched dynamics, TorchRL envs, Gymnasium registration."""

from taskvar_torch.envs.instances import WindyInstances
from taskvar_torch.envs.taxi import TaxiInstances, TaxiModel
from taskvar_torch.envs.taxi_env import TaxiEnv
from taskvar_torch.envs.wargus import WargusConfig, WargusInstances
from taskvar_torch.envs.wargus_env import WargusEnv
from taskvar_torch.envs.windy import WindyLayout, WindyModel, make_layout
from taskvar_torch.envs.windy_env import WindyGridEnv

__all__ = [
    "TaxiEnv",
    "TaxiInstances",
    "TaxiModel",
    "WargusConfig",
    "WargusEnv",
    "WargusInstances",
    "WindyGridEnv",
    "WindyInstances",
    "WindyLayout",
    "WindyModel",
    "make_layout",
]
