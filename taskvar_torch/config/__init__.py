"""Strict experiment configs: frozen dataclasses mirrored by ``configs/*.yaml``
(docs/design.md#configs): :mod:`.schema` (the dataclasses), :mod:`.choices`, :mod:`.validate`,
:mod:`.loader` (YAML -> OmegaConf -> overrides -> frozen dataclass) and :mod:`.help`. Every name
is importable from here, with :func:`atomic_write` and the family helpers.
"""

from taskvar_torch.config.choices import (
    ACTIVATIONS,
    COLLECTOR_BACKENDS,
    HEAD_NETWORKS,
    HIERARCHY_DESCENTS,
    MAX_VALUE_ESTIMATORS,
    METHODS,
    MU_BAR_MODES,
    OPTION_INPUTS,
    ROBUSTNESS_TARGETS,
    ROBUSTNESS_THRESHOLDS,
    ROBUSTNESS_UNTIL,
    ROOT_POLICIES,
    TARGET_UPDATES,
)
from taskvar_torch.config.help import config_help, field_docs
from taskvar_torch.config.loader import (
    apply_overrides,
    config_from_dict,
    config_schema,
    config_to_dict,
    config_to_yaml,
    load_config,
    load_strict,
    save_config_yaml,
)
from taskvar_torch.config.schema import (
    BaselineConfig,
    CollectorConfig,
    Config,
    EnvConfig,
    EvalConfig,
    ExperimentConfig,
    HeadsConfig,
    TrainConfig,
)
from taskvar_torch.contract import FAMILIES, family
from taskvar_torch.io import atomic_write

__all__ = [
    "ACTIVATIONS",
    "COLLECTOR_BACKENDS",
    "FAMILIES",
    "HEAD_NETWORKS",
    "HIERARCHY_DESCENTS",
    "MAX_VALUE_ESTIMATORS",
    "METHODS",
    "MU_BAR_MODES",
    "OPTION_INPUTS",
    "ROBUSTNESS_TARGETS",
    "ROBUSTNESS_THRESHOLDS",
    "ROBUSTNESS_UNTIL",
    "ROOT_POLICIES",
    "TARGET_UPDATES",
    "BaselineConfig",
    "CollectorConfig",
    "Config",
    "EnvConfig",
    "EvalConfig",
    "ExperimentConfig",
    "HeadsConfig",
    "TrainConfig",
    "apply_overrides",
    "atomic_write",
    "config_from_dict",
    "config_help",
    "config_schema",
    "config_to_dict",
    "config_to_yaml",
    "family",
    "field_docs",
    "load_config",
    "load_strict",
    "save_config_yaml",
]
