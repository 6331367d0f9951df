"""Config -> controllers and their calibration: the one place a method's controller is built.

:func:`make_method_controller` turns a config and a head bundle into any of the four methods'
controllers with every setting the config gives (the composed root's policy, the hierarchy's
termination handling, descent metric and thresholds). :func:`calibrate` sets the hierarchy's
per-capability thresholds on *training* states (the replay, or rollouts of the averaging policy on
fresh training instances: :func:`training_states`), never on the nominal test seeds.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.config import Config
from taskvar_torch.controllers import Controller, make_controller
from taskvar_torch.heads.bundle import Heads, with_root_row
from taskvar_torch.heads.networks import head_network
from taskvar_torch.heads.robustness import RobustnessCalibration, calibrate_robustness
from taskvar_torch.subtasks.base import Subtasks

CALIBRATION_STATES = 4096  # training states a calibration reads
TRAINING_STATE_SEED = 1_000_003  # env seed of calibration rollouts (training instances)


def make_method_controller(
    cfg: Config,
    name: str,
    heads: Heads,
    subtasks: Subtasks,
    calibration: RobustnessCalibration | None = None,
) -> Controller:
    """The controller of method ``name`` (averaging, options, interruption, hierarchy) as ``cfg``
    configures it. A hierarchy with ``train.robustness_threshold = "calibrated"`` and no
    ``calibration`` is calibrated on rollouts of the averaging policy (:func:`training_states`)."""
    t = cfg.train
    hierarchy = subtasks.hierarchy
    if name == "hierarchy" and hierarchy is not None:
        if calibration is None and t.robustness_threshold == "calibrated":
            calibration = calibrate(cfg, heads, subtasks, training_states(cfg, heads))
        if t.robustness_threshold == "fixed":
            calibration = None
    return make_controller(
        name,
        heads,
        subtasks,
        hierarchy=hierarchy,
        tau=t.robustness_tau,
        seed=cfg.seed,
        root_policy=t.hierarchy_root_policy,
        terminate=t.hierarchy_termination,
        descent=t.hierarchy_descent,
        calibration=calibration,
    )


@torch.no_grad()
def calibrate(
    cfg: Config, heads: Heads, subtasks: Subtasks, states: TensorDictBase
) -> RobustnessCalibration:
    """Per-capability robustness thresholds and scales on training ``states`` (a tensordict
    ``(B,)`` with the observation and the keys the subtasks read): R(o, s, pi^o(s)) under each
    option's own greedy action (the root's: the averaging head's, with
    ``train.hierarchy_root_policy = "averaging"``). See :class:`RobustnessCalibration`."""
    t = cfg.train
    names = list(heads.option_names)
    obs = states.get(keys.OBSERVATION)
    rob = head_network(heads.heads["robustness"])(obs)  # (B, O, A)
    q_opt = head_network(heads.heads["options"])(obs)  # (B, O, A)
    tree = subtasks.hierarchy
    if t.hierarchy_root_policy == "averaging" and tree is not None:
        q_avg = head_network(heads.heads["averaging"])(obs)  # (B, A)
        q_opt = with_root_row(q_opt, q_avg, names.index(tree.root))
    r = rob.gather(-1, q_opt.argmax(-1, keepdim=True)).squeeze(-1)  # (B, O)
    composed = torch.tensor(
        [tree is not None and not tree.is_leaf(n) for n in names], device=r.device
    )
    return calibrate_robustness(
        r,
        subtasks.startable(states),
        subtasks.no_conflict(states),
        composed,
        t.robustness_keep_share,
        t.robustness_tau,
    )


def replay_states(buffer, n: int = CALIBRATION_STATES) -> TensorDictBase:
    """``n`` states of a replay buffer, evenly spaced over its rows (draws no random numbers, so
    the training stream is untouched)."""
    size = len(buffer)
    idx = torch.linspace(0, size - 1, min(n, size)).round().long()
    return buffer.storage[idx]


@torch.no_grad()
def training_states(
    cfg: Config, heads: Heads, episodes: int = 8, seed: int = TRAINING_STATE_SEED
) -> TensorDictBase:
    """States the greedy averaging policy visits on fresh *training* instances (``env.instances``
    of ``cfg``, env seed ``seed``): ``episodes`` episodes, at most :data:`CALIBRATION_STATES`
    states, evenly spaced."""
    from taskvar_torch.train import make_env  # the env factory lives with the trainer

    env = make_env(cfg, num_envs=episodes, seed=seed)
    td = env.reset()
    state_keys = list(td.exclude(keys.INSTANCE).keys(True, True))
    alive = torch.ones(episodes, dtype=torch.bool, device=td.device)
    seen = []
    net = head_network(heads.heads["averaging"])
    while bool(alive.any()):
        seen.append(td.select(*state_keys)[alive])
        td.set(keys.ACTION, net(td.get(keys.OBSERVATION)).argmax(-1))
        td = env.step(td).get(keys.NEXT)
        alive = alive & ~td.get(keys.DONE).reshape(episodes)
    states = torch.cat(seen)
    idx = torch.linspace(0, states.shape[0] - 1, min(CALIBRATION_STATES, states.shape[0]))
    return states[idx.round().long()]
