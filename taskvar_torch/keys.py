"""The tensordict key vocabulary, declared once (docs/design.md, Vocabulary).

Envs, heads, controllers, learners and experiments import these names rather than spelling strings.
Everything under ``INSTANCE`` is hidden task information: no policy, head or controller reads it;
analysis code may, to group results by instance.
"""

from __future__ import annotations

OBSERVATION = "observation"
ACTION = "action"
REWARD = "reward"
DONE = "done"
TERMINATED = "terminated"
TRUNCATED = "truncated"
NEXT = "next"

# Integer position / event state, kept beside the observation so subtask rewards can be computed
# from raw transitions. Windy: ``cell`` (flat row*W+col). Wargus: see families/wargus/dynamics.py.
CELL = "cell"
STEP_COUNT = "step_count"

INSTANCE = "instance"  # ("instance", name): hidden instance parameters (never in the observation)

# Head outputs (docs/design.md, The ``Heads`` interface): averaging (B, A), options (B, O, A),
# switching (B, O), max-value (B, O), robustness (B, O, A).
ACTION_VALUE = "action_value"
OPTION_ACTION_VALUE = "option_action_value"
OPTION_VALUE = "option_value"
MAX_VALUE = "max_value"
ROBUSTNESS = "robustness"

# Controller carried state and decision traces (paper §3.3-3.4).
OPTION = "option"
RUNNING_OPTION = "running_option"
HIERARCHY_LEVEL = "hierarchy_level"
INTERRUPTED = "interrupted"

# Option controllers' input besides the heads (option-first (O, B) inside the kernels): s_t is in
# option o's initiation set I_o (Subtasks.initiation), the options mu_bar may pick (paper §3.2).
INITIABLE = "initiable"

# Option controllers' input where options act by given policies (Subtasks.given_actions): (B, O)
# int64, each given-policy option's action at s_t (-1 for a learnt option).
GIVEN_ACTION = "given_action"

# Hierarchy inputs besides the heads (option-first inside the kernels): where each option can take
# control (Subtasks.startable), and per-row calibrated thresholds / scales of the robustness critics.
STARTABLE = "startable"
ROBUSTNESS_TAU = "robustness_tau"
ROBUSTNESS_SCALE = "robustness_scale"
