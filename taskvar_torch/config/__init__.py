"""Strict experiment configs: frozen dataclasses mirrored by ``configs/*.yaml`` (docs/design.md,
Configs).

- :mod:`~taskvar_torch.config.schema`: the dataclasses (:class:`Config` and its sections), each
  field with a docstring;
- :mod:`~taskvar_torch.config.choices`: the allowed values of the choice fields and
  :data:`METHODS`;
- :mod:`~taskvar_torch.config.validate`: the range and choice checks run on construction;
- :mod:`~taskvar_torch.config.loader`: YAML file -> OmegaConf structured schema -> overrides ->
  frozen dataclass, for any config dataclass, with one-line errors naming the dotted key;
- :mod:`~taskvar_torch.config.help`: ``--help`` text from the field docstrings.

Every name is importable from ``taskvar_torch.config`` itself, as are :func:`atomic_write`
(``taskvar_torch/io.py``) and the family helpers the config is read through
(``taskvar_torch/contract.py``).

Examples:
    >>> cfg = load_config("configs/windy.yaml", ["train.lr=0.01"])
    >>> cfg.train.lr
    0.01
    >>> config_from_dict(config_to_dict(cfg)) == cfg
    True
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
