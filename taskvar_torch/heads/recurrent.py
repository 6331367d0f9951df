"""Baselines beside the paper's methods (issue 31): a recurrent Q-network and an instance-informed
ceiling, built from TorchRL's own modules (docs/memory.md).

* ``recurrent`` (DRQN; the in-context adaptation of RL^2-style meta-RL): a TorchRL
  :class:`~torchrl.modules.GRUModule` over the observation sequence, an MLP Q head and a
  :class:`~torchrl.modules.QValueModule`. Its weights are frozen at test time, like the paper's
  controllers (§3: no learning online), but its hidden state can infer the hidden instance from
  the trajectory (a gust, a sighting), which no memoryless controller of the paper can.
* ``informed``: a feed-forward Q-network reading the observation *and* the family's features of
  the hidden instance (:func:`informed_features`; windy: p and the direction, Taxi: rain and
  fickleness, Wargus: the full state, every item's and patrol's position). It is the learnt
  ceiling: the paper's averaging head (§3.1) given what the paper's agent never sees.

Both are greedy in their Q-values at evaluation (:class:`BaselineController`), act step by step
on the batched env (the recurrent one resets its hidden state at every episode start through
TorchRL's ``InitTracker`` and the GRU's tensordict primer) and are saved as their own bundles
(``DIR/recurrent.pt``, ``DIR/informed.pt``: :func:`save_baseline`, :func:`load_baseline`), loadable
with ``torch.load(weights_only=True)``. Training: :mod:`taskvar_torch.train_recurrent`.
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
from torchrl.modules import MLP, GRUModule, QValueModule

from taskvar_torch import keys
from taskvar_torch.checkpoint import CheckpointError, load_checkpoint, make_bundle, save_checkpoint
from taskvar_torch.config import Config, config_from_dict

BASELINES = ("recurrent", "informed")
"""The baseline methods, in the order ``taskvar eval --method all`` plays them after the paper's."""

EMBED = "recurrent_embed"
"""Key of the GRU's output (the Q head's input)."""
RECURRENT_STATE = "recurrent_state"
"""Key of the GRU's carried hidden state (``("next", RECURRENT_STATE)`` after a step)."""
PREV_ACTION = "prev_action"
"""Key of the previous action, one-hot (zeros at an episode's first step): :class:`PreviousAction`."""
GRU_INPUT = "recurrent_input"
"""Key of the GRU's input: the observation and the previous action."""
INSTANCE_FEATURES = "instance_features"
"""Key of the informed head's instance features (:func:`informed_features`)."""

_ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "silu": nn.SiLU}


@dataclass(frozen=True)
class BaselineSettings:
    """Settings of both baselines (``baseline.KEY=V`` on ``taskvar train-baselines``).

    The defaults were chosen on *training* instances only (the corridor of tests/test_recurrent.py
    and configs/windy.yaml's training distribution, never a test distribution or shift); every
    other setting (frames, batch, gamma, epsilon schedule, buffer, gradient clipping) is the
    config's ``train`` section, the same as the paper's heads get.

    Attributes:
        hidden: GRU hidden size (recurrent).
        mlp: hidden layers of the Q head (recurrent: after the GRU; informed: the whole network).
        slice_len: length of the replay slices (``SliceSampler``) the recurrent head learns on;
            slices stay within one episode and start from the hidden state stored at collection.
        lr: Adam learning rate; ``None``: the config's ``train.lr``.
        updates_per_batch: gradient steps per collected batch; ``None``: ``train.updates_per_batch``.
        target_tau: Polyak rate of the target network (TorchRL ``SoftUpdate``); ``None``:
            ``train.target_tau``.
    """

    hidden: int = 64
    mlp: tuple[int, ...] = (64,)
    slice_len: int = 8
    lr: float | None = None
    updates_per_batch: int | None = None
    target_tau: float | None = None

    def __post_init__(self) -> None:
        if int(self.hidden) < 1:
            raise ValueError(f"baseline.hidden must be >= 1, got {self.hidden}")
        if int(self.slice_len) < 1:
            raise ValueError(f"baseline.slice_len must be >= 1, got {self.slice_len}")
        if self.lr is not None and not float(self.lr) > 0:
            raise ValueError(f"baseline.lr must be > 0, got {self.lr}")
        if self.updates_per_batch is not None and int(self.updates_per_batch) < 1:
            raise ValueError(
                f"baseline.updates_per_batch must be >= 1, got {self.updates_per_batch}"
            )
        if self.target_tau is not None and not 0 < float(self.target_tau) <= 1:
            raise ValueError(f"baseline.target_tau must be in (0, 1], got {self.target_tau}")
        if any(int(h) < 1 for h in self.mlp):
            raise ValueError(f"baseline.mlp sizes must be >= 1, got {list(self.mlp)}")

    @classmethod
    def from_overrides(cls, items: list[str] | tuple[str, ...]) -> BaselineSettings:
        """Settings from ``KEY=V`` strings (``hidden=32``, ``mlp=64+64``, ``lr=0.001``); an unknown
        key or a bad value is a one-line ``ValueError``."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        out: dict[str, Any] = {}
        for item in items:
            k, sep, v = item.partition("=")
            if not sep or k not in fields:
                raise ValueError(
                    f"baseline.{k} is not a baseline setting; known: "
                    f"{', '.join('baseline.' + n for n in fields)}"
                )
            try:
                if k == "mlp":
                    out[k] = tuple(int(x) for x in v.split("+") if x)
                elif v.lower() in ("null", "none"):
                    out[k] = None
                elif k in ("lr", "target_tau"):
                    out[k] = float(v)
                else:
                    out[k] = int(v)
            except ValueError:
                raise ValueError(f"baseline.{k}={v!r} is not a valid value") from None
        return cls(**out)


class PreviousAction(Transform):
    """Env transform writing the action just taken, one-hot, as ``prev_action`` of the next step
    (zeros after a reset, partial resets included).

    The recurrent head reads it beside the observation (as DRQN and RL^2 agents do): under
    epsilon-greedy exploration the same observations can follow different actions, and an
    observation alone does not say what the agent tried (on the corridor, being back at S says
    the wind opposes the move *just made*). It is env-side, so the replay holds the action
    actually taken, not the network's greedy one.
    """

    def __init__(self, num_actions: int, out_key: str = PREV_ACTION):
        super().__init__(in_keys=[keys.ACTION], out_keys=[out_key])
        self.num_actions = int(num_actions)

    def _one_hot(self, action: torch.Tensor) -> torch.Tensor:
        return nn.functional.one_hot(action.long(), self.num_actions).to(torch.float32)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.out_keys[0], self._one_hot(tensordict.get(keys.ACTION)))
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        shape = (*tensordict_reset.batch_size, self.num_actions)
        zeros = torch.zeros(shape, device=tensordict_reset.device)
        reset = None if tensordict is None else tensordict.get("_reset", None)
        prev = None if tensordict is None else tensordict.get(self.out_keys[0], None)
        if reset is not None and prev is not None:  # a partial reset keeps the others' entry
            zeros = torch.where(reset.reshape(*tensordict_reset.batch_size, 1), zeros, prev)
        tensordict_reset.set(self.out_keys[0], zeros)
        return tensordict_reset

    def transform_observation_spec(self, observation_spec):
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*observation_spec.shape, self.num_actions),
            dtype=torch.float32,
            device=observation_spec.device,
        )
        return observation_spec


class InstanceFeatures(TensorDictModuleBase):
    """Writes the family's informed features (:func:`informed_features`) of the tensordict's
    ``("instance", ...)`` entries as ``instance_features`` ``(*batch, F)`` (any batch shape; the
    family function sees a flat batch). Only the ``informed`` baseline reads them: the hidden
    instance, given away on purpose."""

    def __init__(self, features: Callable[[TensorDictBase], torch.Tensor], instance_keys):
        super().__init__()
        self.features = features
        self.in_keys = [(keys.INSTANCE, k) for k in instance_keys]
        self.out_keys = [INSTANCE_FEATURES]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        flat = td.reshape(-1) if td.batch_dims != 1 else td
        f = self.features(flat)
        td.set(INSTANCE_FEATURES, f.reshape(*td.batch_size, f.shape[-1]))
        return td


class _Concat(nn.Module):
    def forward(self, obs: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        return torch.cat([obs, feats.to(obs.dtype)], -1)


def _mlp(in_features: int, out_features: int, cells: tuple[int, ...], activation: str) -> nn.Module:
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(cells),
        activation_class=_ACTIVATIONS.get(activation, nn.ReLU),
    )


def make_recurrent_qnet(
    obs_dim: int, num_actions: int, settings: BaselineSettings, activation: str = "relu"
) -> tuple[TensorDictSequential, GRUModule]:
    """The recurrent Q-network: ``GRUModule([observation, prev_action]) -> MLP -> QValueModule``
    (greedy ``action`` and ``action_value``), as in TorchRL's recurrent DQN tutorial; returns the
    policy and its GRU (the env needs ``InitTracker``, :class:`PreviousAction` and the GRU's
    ``make_tensordict_primer()``: :func:`recurrent_transforms`)."""
    gru = GRUModule(
        input_size=obs_dim + num_actions,
        hidden_size=int(settings.hidden),
        in_keys=[GRU_INPUT, RECURRENT_STATE],
        out_keys=[EMBED, (keys.NEXT, RECURRENT_STATE)],
    )
    cat = TensorDictModule(_Concat(), in_keys=[keys.OBSERVATION, PREV_ACTION], out_keys=[GRU_INPUT])
    head = TensorDictModule(
        _mlp(int(settings.hidden), num_actions, tuple(settings.mlp), activation),
        in_keys=[EMBED],
        out_keys=[keys.ACTION_VALUE],
    )
    qv = QValueModule(action_space="categorical", action_value_key=keys.ACTION_VALUE)
    return TensorDictSequential(cat, gru, head, qv), gru


def recurrent_transforms(gru: GRUModule, num_actions: int) -> Compose:
    """What the recurrent head needs on its env: episode starts (``InitTracker``), the previous
    action and the GRU's hidden state, zeroed at every (partial) reset."""
    return Compose(InitTracker(), PreviousAction(num_actions), gru.make_tensordict_primer())


def make_informed_qnet(
    obs_dim: int,
    num_actions: int,
    instance_dim: int,
    features: Callable[[TensorDictBase], torch.Tensor],
    instance_keys: tuple[str, ...],
    settings: BaselineSettings,
    activation: str = "relu",
) -> TensorDictSequential:
    """The informed Q-network: ``[observation, instance_features] -> MLP -> QValueModule``."""
    net = TensorDictSequential(
        InstanceFeatures(features, instance_keys),
        TensorDictModule(_Concat(), in_keys=[keys.OBSERVATION, INSTANCE_FEATURES], out_keys=["x"]),
        TensorDictModule(
            _mlp(obs_dim + instance_dim, num_actions, tuple(settings.mlp), activation),
            in_keys=["x"],
            out_keys=[keys.ACTION_VALUE],
        ),
        QValueModule(action_space="categorical", action_value_key=keys.ACTION_VALUE),
    )
    return net


def family_instance_keys(cfg: Config) -> tuple[str, ...]:
    """The ``("instance", key)`` fields of the family's env (read from a one-env probe)."""
    from taskvar_torch.factory import make_env

    env = make_env(cfg, 1)
    return tuple(
        k[1]
        for k in env.observation_spec.keys(True, True)
        if isinstance(k, tuple) and len(k) == 2 and k[0] == keys.INSTANCE
    )


def informed_features(cfg: Config) -> tuple[int, Callable[[TensorDictBase], torch.Tensor]]:
    """``(dim, features)`` the informed head reads for the config's family: its
    ``Family.informed_features(cfg)`` (Wargus: item and patrol positions, a dimension set by the
    config), else ``(instance_dim, instance_features)`` (windy, Taxi); a one-line ``ValueError``
    where the family gives neither (then the informed head is unavailable)."""
    from taskvar_torch.families import family

    fam = family(cfg)
    if fam.informed_features is not None:
        dim, feats = fam.informed_features(cfg)
        return int(dim), feats
    if fam.instance_dim is None or fam.instance_features is None:
        raise ValueError(
            f"the informed baseline needs the family's features of the hidden instance "
            f"(Family.informed_features or instance_features); family {fam.name!r} has none, so "
            f"it is unavailable"
        )
    return int(fam.instance_dim), fam.instance_features


@dataclass
class BaselineSpec:
    """What a baseline bundle records beside its weights: enough to rebuild the network."""

    method: str
    obs_dim: int
    num_actions: int
    settings: BaselineSettings
    instance_dim: int = 0
    instance_keys: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["settings"] = {
            k: (list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(self.settings).items()
        }
        d["instance_keys"] = list(self.instance_keys)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BaselineSpec:
        s = dict(d["settings"])
        s["mlp"] = tuple(s.get("mlp", ()))
        return cls(
            method=str(d["method"]),
            obs_dim=int(d["obs_dim"]),
            num_actions=int(d["num_actions"]),
            settings=BaselineSettings(**s),
            instance_dim=int(d.get("instance_dim", 0)),
            instance_keys=tuple(d.get("instance_keys", ())),
        )


def build_baseline(spec: BaselineSpec, cfg: Config) -> TensorDictSequential:
    """The network of ``spec`` (untrained)."""
    act = cfg.heads.activation
    if spec.method == "recurrent":
        return make_recurrent_qnet(spec.obs_dim, spec.num_actions, spec.settings, act)[0]
    if spec.method == "informed":
        _, feats = informed_features(cfg)
        return make_informed_qnet(
            spec.obs_dim,
            spec.num_actions,
            spec.instance_dim,
            feats,
            spec.instance_keys,
            spec.settings,
            act,
        )
    raise ValueError(f"baseline method must be one of {list(BASELINES)}, got {spec.method!r}")


class BaselineController(TensorDictModuleBase):
    """A trained baseline acting greedily, one batched decision per step (no learning online).

    Usable wherever the evaluation code plays a TorchRL policy: ``TransformedEnv(env,
    ctrl.primer())`` adds what it carries (the recurrent head: ``InitTracker`` and the GRU's
    primer, so the hidden state is zero at every episode start, partial resets included), then
    ``ctrl(td)`` writes ``action`` and ``action_value``.
    """

    def __init__(self, net: TensorDictSequential, spec: BaselineSpec):
        super().__init__()
        self.net = net
        self.spec = spec
        self.name = spec.method
        self.in_keys = list(net.in_keys)
        self.out_keys = list(net.out_keys)

    def primer(self) -> Transform:
        """The env transforms this controller needs (empty for ``informed``)."""
        if self.spec.method != "recurrent":
            return Compose()
        gru = next(m for m in self.net.modules() if isinstance(m, GRUModule))
        return recurrent_transforms(gru, self.spec.num_actions)

    @torch.no_grad()
    def forward(self, td: TensorDictBase) -> TensorDictBase:
        return self.net(td)


BUNDLE_NAMES = {"recurrent": "recurrent.pt", "informed": "informed.pt"}
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
    return BaselineController(net.to(device).eval(), spec), cfg


__all__ = [
    "BASELINES",
    "BUNDLE_NAMES",
    "BaselineController",
    "BaselineSettings",
    "BaselineSpec",
    "InstanceFeatures",
    "PreviousAction",
    "baseline_path",
    "build_baseline",
    "family_instance_keys",
    "informed_features",
    "load_baseline",
    "make_informed_qnet",
    "make_recurrent_qnet",
    "recurrent_transforms",
    "save_baseline",
]
