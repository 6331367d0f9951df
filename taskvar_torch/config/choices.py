"""The allowed values of the config's choice fields, and the paper's method list (below
:mod:`.schema` and :mod:`.validate`, which both read them).
"""

from __future__ import annotations

METHODS = ("averaging", "options", "interruption", "hierarchy")
"""The paper's four controllers, in its order: averaging (§3.1), options (§3.2), interruption
(Algorithm 1), hierarchy (Algorithm 2). The experiments iterate them in this order; the windy
Figure 2 takes all but hierarchy (families/windy/fig2.py)."""

ACTIVATIONS = ("elu", "gelu", "relu", "silu", "tanh")
HEAD_NETWORKS = ("mlp", "conv")  # taskvar_torch/heads/networks.py NETWORKS
OPTION_INPUTS = ("full", "subtask")
TARGET_UPDATES = ("hard", "soft")
MU_BAR_MODES = ("greedy", "softmax")
MAX_VALUE_ESTIMATORS = ("expectile", "instance")
ROBUSTNESS_TARGETS = ("greedy", "option")  # mirrors heads/robustness.py
ROOT_POLICIES = ("averaging", "option")  # mirrors controllers/base.py
ROBUSTNESS_THRESHOLDS = ("calibrated", "fixed")
ROBUSTNESS_UNTIL = ("episode", "termination")  # mirrors heads/robustness.py
HIERARCHY_DESCENTS = ("normalised", "raw")  # mirrors controllers/hierarchy.py
COLLECTOR_BACKENDS = ("process", "ray")  # taskvar_torch/training/collection.py make_collector
MATMUL_DTYPES = ("bfloat16", "float32")  # mirrors heads/learner.py MATMUL_DTYPES
REPLAY_SAMPLINGS = ("uniform", "per_option")  # taskvar_torch/training/replay.py make_replay_buffer
LOGGERS = ("csv", "mlflow", "tensorboard", "wandb")  # taskvar_torch/training/run_logs.py RunLoggers
