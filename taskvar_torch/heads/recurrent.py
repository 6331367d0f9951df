"""Baselines beside the paper's methods, built from TorchRL's own modules
(docs/memory.md#what-they-are).

``recurrent`` (DRQN): a :class:`~torchrl.modules.GRUModule` over the observation, previous action
and previous reward, an MLP Q head and a :class:`~torchrl.modules.QValueModule`; frozen at test time
like the paper's controllers (§3), but its hidden state can infer the instance. ``informed``: a
feed-forward Q-network over the observation and the instance features, the ceiling candidate.
``blind``: the same with the features zeroed. All act greedily (:class:`BaselineController`) and are
saved as plain-data bundles (:func:`save_baseline`, :func:`load_baseline`). Training:
:mod:`taskvar_torch.training.baselines`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Unbounded
from torchrl.envs import Compose, InitTracker, Transform
from torchrl.modules import GRUModule, QValueModule

from taskvar_torch import keys
from taskvar_torch.checkpoint import CheckpointError, load_checkpoint, make_bundle, save_checkpoint
from taskvar_torch.config import Config, config_from_dict
from taskvar_torch.heads.informed import INSTANCE_FEATURES, ResidualInformedQ, informed_features
from taskvar_torch.heads.networks import make_mlp

BASELINES = ("recurrent", "informed", "blind")
"""The baseline methods, in the order ``taskvar eval --method all`` plays them after the paper's."""
SEES_MORE = ("recurrent", "informed")
"""The baselines that see more than the observation (the episode so far; the hidden instance):
every other method, ``blind`` included, is memoryless."""

EMBED = "recurrent_embed"
"""Key of the GRU's output (the Q head's input)."""
RECURRENT_STATE = "recurrent_state"
"""Key of the GRU's carried hidden state (``("next", RECURRENT_STATE)`` after a step)."""
PREV_ACTION = "prev_action"
"""Key of the previous action, one-hot (zeros at an episode's first step): :class:`PreviousStep`."""
PREV_REWARD = "prev_reward"
"""Key of the previous reward ``(..., 1)`` (zero at an episode's first step): :class:`PreviousStep`."""
GRU_INPUT = "recurrent_input"
"""Key of the GRU's input: the observation, the previous action and (by default) reward."""


class PreviousStep(Transform):
    """Env transform writing the action just taken, one-hot, as the next step's ``prev_action`` and
    (``reward=True``) its reward as ``prev_reward`` (zeros after a reset, partial resets included).
    """

    def __init__(self, num_actions: int, reward: bool = True):
        out = [PREV_ACTION, PREV_REWARD] if reward else [PREV_ACTION]
        super().__init__(in_keys=[keys.ACTION], out_keys=out)
        self.num_actions = int(num_actions)
        self.reward = bool(reward)

    def _one_hot(self, action: torch.Tensor) -> torch.Tensor:
        return nn.functional.one_hot(action.long(), self.num_actions).to(torch.float32)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(PREV_ACTION, self._one_hot(tensordict.get(keys.ACTION)))
        if self.reward:
            reward = next_tensordict.get(keys.REWARD).to(torch.float32)
            next_tensordict.set(PREV_REWARD, reward.reshape(*next_tensordict.batch_size, 1))
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        for key, width in zip(self.out_keys, (self.num_actions, 1)):
            zeros = torch.zeros(
                (*tensordict_reset.batch_size, width), device=tensordict_reset.device
            )
            prev = None if tensordict is None else tensordict.get(key, None)
            if reset is not None and prev is not None:  # a partial reset keeps the others' entry
                zeros = torch.where(reset.reshape(*tensordict_reset.batch_size, 1), zeros, prev)
            tensordict_reset.set(key, zeros)
        return tensordict_reset

    def transform_observation_spec(self, observation_spec):
        for key, width in zip(self.out_keys, (self.num_actions, 1)):
            observation_spec[key] = Unbounded(
                shape=(*observation_spec.shape, width),
                dtype=torch.float32,
                device=observation_spec.device,
            )
        return observation_spec


class InstanceFeatures(TensorDictModuleBase):
    """Writes :func:`informed_features` of the tensordict's ``("instance", ...)`` entries as
    ``instance_features (*batch, F)``; ``blind=True`` writes zeros of the same shape.
    """

    def __init__(
        self,
        features: Callable[[TensorDictBase], torch.Tensor],
        instance_keys,
        blind: bool = False,
    ):
        super().__init__()
        self.features = features
        self.blind = bool(blind)
        self.in_keys = [(keys.INSTANCE, k) for k in instance_keys]
        self.out_keys = [INSTANCE_FEATURES]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        flat = td.reshape(-1) if td.batch_dims != 1 else td
        f = self.features(flat)
        if self.blind:
            f = torch.zeros_like(f)
        td.set(INSTANCE_FEATURES, f.reshape(*td.batch_size, f.shape[-1]))
        return td


class PaddedGRU(nn.RNNBase):
    """``nn.GRU``'s weights (same names) and arithmetic, one layer, batch first, for
    ``GRUModule(gru=)``: in recurrent mode it takes padded slices with a mask instead of a packed
    sequence (a packed GRU's backward on CPU refills a zero copy of the input projection every time
    step). Same outputs.
    """

    def __init__(self, input_size: int, hidden_size: int):
        super().__init__("GRU", input_size, hidden_size, batch_first=True)

    def forward(
        self, input: torch.Tensor, hx: torch.Tensor | None = None, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if hx is None:
            hx = input.new_zeros(1, input.shape[0], self.hidden_size)
        weights = [getattr(self, name) for name in self._flat_weights_names]
        x = input.transpose(0, 1).contiguous()  # time-major: one matmul for the input projection
        y, h = torch.gru(x, hx, weights, True, 1, 0.0, self.training, False, False)
        y = y.transpose(0, 1)
        if mask is not None:  # (B, T): each slice's last step
            last = mask.sum(1) - 1
            h = y[torch.arange(y.shape[0], device=y.device), last].unsqueeze(0)
        return y, h


class _Concat(nn.Module):
    def forward(self, *xs: torch.Tensor) -> torch.Tensor:
        return torch.cat([x.to(xs[0].dtype) for x in xs], -1)


def make_recurrent_qnet(
    obs_dim: int,
    num_actions: int,
    hidden: int,
    mlp: tuple[int, ...],
    activation: str = "relu",
    prev_reward: bool = True,
) -> tuple[TensorDictSequential, GRUModule]:
    """The recurrent Q-network ``GRUModule([observation, prev_action, prev_reward]) -> MLP ->
    QValueModule``; returns the policy and its GRU (the env needs :func:`recurrent_transforms`).
    ``prev_reward=False``: bundles written before the reward was an input.
    """
    inputs = [keys.OBSERVATION, PREV_ACTION] + ([PREV_REWARD] if prev_reward else [])
    gru = GRUModule(
        gru=PaddedGRU(obs_dim + num_actions + int(prev_reward), int(hidden)),
        in_keys=[GRU_INPUT, RECURRENT_STATE],
        out_keys=[EMBED, (keys.NEXT, RECURRENT_STATE)],
    )
    cat = TensorDictModule(_Concat(), in_keys=inputs, out_keys=[GRU_INPUT])
    head = TensorDictModule(
        make_mlp(int(hidden), num_actions, tuple(mlp), activation),
        in_keys=[EMBED],
        out_keys=[keys.ACTION_VALUE],
    )
    qv = QValueModule(action_space="categorical", action_value_key=keys.ACTION_VALUE)
    return TensorDictSequential(cat, gru, head, qv), gru


def recurrent_transforms(gru: GRUModule, num_actions: int, prev_reward: bool = True) -> Compose:
    """What the recurrent head needs on its env: episode starts (``InitTracker``), the previous
    action (and reward) and the GRU's hidden state, zeroed at every (partial) reset."""
    return Compose(
        InitTracker(), PreviousStep(num_actions, prev_reward), gru.make_tensordict_primer()
    )


def make_informed_qnet(
    obs_dim: int,
    num_actions: int,
    instance_dim: int,
    features: Callable[[TensorDictBase], torch.Tensor],
    instance_keys: tuple[str, ...],
    mlp: tuple[int, ...],
    activation: str = "relu",
    residual: bool = False,
    blind: bool = False,
) -> TensorDictSequential:
    """The informed Q-network ``[observation, instance_features] -> MLP -> QValueModule``; ``blind``
    zeroes the features; ``residual`` builds old bundles' ``Q_avg + Delta``
    (:class:`~taskvar_torch.heads.informed.ResidualInformedQ`), which still evaluate.
    """
    if residual:
        return TensorDictSequential(
            InstanceFeatures(features, instance_keys),
            TensorDictModule(
                ResidualInformedQ(
                    make_mlp(obs_dim, num_actions, tuple(mlp), activation),
                    make_mlp(obs_dim + instance_dim, num_actions, tuple(mlp), activation),
                ),
                in_keys=[keys.OBSERVATION, INSTANCE_FEATURES],
                out_keys=[keys.ACTION_VALUE],
            ),
            QValueModule(action_space="categorical", action_value_key=keys.ACTION_VALUE),
        )
    return TensorDictSequential(
        InstanceFeatures(features, instance_keys, blind),
        TensorDictModule(_Concat(), in_keys=[keys.OBSERVATION, INSTANCE_FEATURES], out_keys=["x"]),
        TensorDictModule(
            make_mlp(obs_dim + instance_dim, num_actions, tuple(mlp), activation),
            in_keys=["x"],
            out_keys=[keys.ACTION_VALUE],
        ),
        QValueModule(action_space="categorical", action_value_key=keys.ACTION_VALUE),
    )


@dataclass
class BaselineSpec:
    """What a baseline bundle records beside its weights: enough to rebuild the network.

    Attributes:
        method: ``recurrent``, ``informed`` or ``blind``.
        obs_dim, num_actions: the family's observation width and number of actions.
        mlp: hidden widths of the Q head (recurrent: after the GRU).
        hidden: GRU hidden size (recurrent only).
        instance_dim, instance_keys: the informed network's feature width and the ``("instance",
            key)`` entries they are read from.
        prev_reward: the recurrent network reads the previous reward (``False`` for old bundles).
        residual: an old informed bundle's ``Q_avg + Delta`` form (``False`` for new ones).
    """

    method: str
    obs_dim: int
    num_actions: int
    mlp: tuple[int, ...]
    hidden: int = 0
    instance_dim: int = 0
    instance_keys: tuple[str, ...] = ()
    prev_reward: bool = True
    residual: bool = False

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["mlp"] = [int(h) for h in self.mlp]
        d["instance_keys"] = list(self.instance_keys)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BaselineSpec:
        """The spec of a bundle's ``baseline_spec`` (also the layout written before settings were
        single-sourced: ``{"settings": {"hidden", "mlp", ...}}``, no previous reward)."""
        old = d.get("settings")
        if isinstance(old, dict):
            mlp, hidden, prev_reward = old.get("mlp", ()), old.get("hidden", 0), False
        else:
            mlp, hidden, prev_reward = d["mlp"], d.get("hidden", 0), d.get("prev_reward", True)
        return cls(
            method=str(d["method"]),
            obs_dim=int(d["obs_dim"]),
            num_actions=int(d["num_actions"]),
            mlp=tuple(int(h) for h in mlp),
            hidden=int(hidden),
            instance_dim=int(d.get("instance_dim", 0)),
            instance_keys=tuple(d.get("instance_keys", ())),
            prev_reward=bool(prev_reward),
            residual=bool(d.get("residual", False)),
        )


def build_baseline(spec: BaselineSpec, cfg: Config) -> TensorDictSequential:
    """The network of ``spec`` (untrained)."""
    act = cfg.heads.activation
    if spec.method == "recurrent":
        return make_recurrent_qnet(
            spec.obs_dim, spec.num_actions, spec.hidden, spec.mlp, act, spec.prev_reward
        )[0]
    if spec.method in ("informed", "blind"):
        _, feats = informed_features(cfg)
        return make_informed_qnet(
            spec.obs_dim,
            spec.num_actions,
            spec.instance_dim,
            feats,
            spec.instance_keys,
            spec.mlp,
            act,
            spec.residual,
            blind=spec.method == "blind",
        )
    raise ValueError(f"baseline method must be one of {list(BASELINES)}, got {spec.method!r}")


class BaselineController(TensorDictModuleBase):
    """A trained baseline acting greedily, one batched decision per step (no learning online):
    ``TransformedEnv(env, ctrl.primer())``, then ``ctrl(td)`` writes ``action`` and
    ``action_value``.
    """

    def __init__(self, net: TensorDictSequential, spec: BaselineSpec):
        super().__init__()
        self.net = net
        self.spec = spec
        self.name = spec.method
        self.total_frames: int | None = None  # its training budget, set by load_baseline
        self.in_keys = list(net.in_keys)
        self.out_keys = list(net.out_keys)

    def primer(self) -> Transform:
        """The env transforms this controller needs (empty for ``informed`` and ``blind``)."""
        if self.spec.method != "recurrent":
            return Compose()
        gru = next(m for m in self.net.modules() if isinstance(m, GRUModule))
        return recurrent_transforms(gru, self.spec.num_actions, self.spec.prev_reward)

    @torch.no_grad()
    def forward(self, td: TensorDictBase) -> TensorDictBase:
        return self.net(td)


BUNDLE_NAMES = {"recurrent": "recurrent.pt", "informed": "informed.pt", "blind": "blind.pt"}
"""File name of each baseline's bundle beside ``final.pt``."""


def baseline_path(checkpoint: str | os.PathLike, method: str) -> Path:
    """Where ``method``'s bundle lives for a bundle at ``checkpoint`` (same folder)."""
    return Path(checkpoint).with_name(BUNDLE_NAMES[method])


def save_baseline(
    path: str | os.PathLike,
    net: nn.Module,
    spec: BaselineSpec,
    cfg: Config,
    counters: dict[str, Any] | None = None,
) -> Path:
    """Write a baseline bundle atomically (``checkpoint.save_checkpoint``): its weights under
    ``models[method]``, its ``baseline_spec`` and the config; plain data only."""
    bundle = make_bundle(
        cfg,
        models={spec.method: net},
        counters=dict(counters or {}),
        rng={},
        baseline_spec=spec.to_dict(),
    )
    return save_checkpoint(path, bundle)


def load_baseline(
    path: str | os.PathLike, device: str | torch.device = "cpu"
) -> tuple[BaselineController, Config]:
    """The greedy controller and config of a baseline bundle (``torch.load(weights_only=True)``);
    a file that is not one is a one-line :class:`CheckpointError`."""
    bundle = load_checkpoint(path)
    if not isinstance(bundle.get("baseline_spec"), dict):
        raise CheckpointError(f"{str(path)!r} is not a baseline bundle (it has no baseline_spec)")
    spec = BaselineSpec.from_dict(bundle["baseline_spec"])
    cfg = config_from_dict(bundle["config"], f"baseline bundle {path}")
    net = build_baseline(spec, cfg)
    state = bundle.get("models", {}).get(spec.method)
    if state is None:
        raise CheckpointError(f"{str(path)!r} has no weights for {spec.method!r}")
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(v.isfinite().all())]
    if bad:
        raise CheckpointError(f"{str(path)!r} has non-finite weights ({bad[0]}): its run diverged")
    try:
        net.load_state_dict(state)
    except (RuntimeError, KeyError) as e:
        raise CheckpointError(
            f"{str(path)!r} weights do not fit its spec: {str(e).splitlines()[0]}"
        ) from None
    ctrl = BaselineController(net.to(device).eval(), spec)
    budget = bundle.get("counters", {}).get("budget")  # its frame budget (baseline_budget)
    ctrl.total_frames = int(budget) if budget is not None else int(cfg.train.total_frames)
    return ctrl, cfg


__all__ = [
    "BASELINES",
    "SEES_MORE",
    "BUNDLE_NAMES",
    "PREV_ACTION",
    "PREV_REWARD",
    "RECURRENT_STATE",
    "BaselineController",
    "BaselineSpec",
    "InstanceFeatures",
    "PaddedGRU",
    "PreviousStep",
    "baseline_path",
    "build_baseline",
    "load_baseline",
    "make_informed_qnet",
    "make_recurrent_qnet",
    "recurrent_transforms",
    "save_baseline",
]
