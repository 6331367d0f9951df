"""Config -> everything a run is made of: the one place envs, options, heads, learners and
controllers are built (as TorchRL's ``sota-implementations/*/utils.py``).

:func:`make_env` and :func:`make_subtasks` go through the family registry; :func:`build_heads`
builds fresh heads from a :class:`HeadSpec`; :func:`make_learner` the fused learner;
:func:`make_method_controller` a method's controller with every setting the config gives
(docs/design.md#controllers), calibrated on training states (:func:`training_states`), never on test
seeds; :func:`load_heads` a trained bundle's heads and config.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.envs import EnvBase

from taskvar_torch import keys
from taskvar_torch.checkpoint import (
    CheckpointError,
    evaluation_heads_key,
    is_training_checkpoint,
    load_checkpoint,
    make_bundle,
    require_finite_heads,
    save_checkpoint,
)
from taskvar_torch.checkpoint.checks import load_state_dicts
from taskvar_torch.config import Config, config_from_dict
from taskvar_torch.config.controller import check_controller_overrides, with_controller_settings
from taskvar_torch.config.memory import check_memory
from taskvar_torch.config.memory import estimate as estimate_memory
from taskvar_torch.contract import FAMILIES, family
from taskvar_torch.controllers import Controller, make_controller
from taskvar_torch.envs.episodes import run_episodes
from taskvar_torch.heads.bundle import Heads, with_root_row
from taskvar_torch.heads.learner import MultiHeadLearner, MultiHeadLoss
from taskvar_torch.heads.max_value import OptimismGapHead, make_instance_critic
from taskvar_torch.heads.networks import head_network, make_stacked_heads
from taskvar_torch.heads.relabel import has_robustness
from taskvar_torch.heads.robustness import RobustnessCalibration, calibrate_robustness
from taskvar_torch.heads.switching import mu_bar_temperature
from taskvar_torch.run_folder import ResultsFolder, check_out_path
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
    configures it; a hierarchy with ``train.robustness_threshold = "calibrated"`` and no
    ``calibration`` is calibrated on :func:`training_states`.
    """
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
    """:class:`RobustnessCalibration` on training ``states (B,)``: R(o, s, pi^o(s)) under each
    option's own greedy action (the root's per ``train.hierarchy_root_policy``).
    """
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
    """At most :data:`CALIBRATION_STATES` states, evenly spaced, that the greedy averaging policy
    visits in ``episodes`` episodes on fresh training instances (env seed ``seed``).
    """
    env = make_env(cfg, num_envs=episodes, seed=seed)
    net = head_network(heads.heads["averaging"])
    greedy = TensorDictModule(lambda obs: net(obs).argmax(-1), [keys.OBSERVATION], [keys.ACTION])
    seen: list[TensorDictBase] = []
    state_keys: list = []  # the reset's keys but the instance

    def visit(td: TensorDictBase, alive: torch.Tensor) -> None:
        if not state_keys:
            state_keys.extend(td.exclude(keys.INSTANCE, keys.ACTION, keys.NEXT).keys(True, True))
        seen.append(td.select(*state_keys)[alive])  # the states acted in

    run_episodes(env, greedy, on_step=visit)
    states = torch.cat(seen)
    idx = torch.linspace(0, states.shape[0] - 1, min(CALIBRATION_STATES, states.shape[0]))
    return states[idx.round().long()]


# --------------------------------------------------------------------------------------------
# envs and options


def check_family_installed(cfg: Config, what: str) -> None:
    """A one-line ``ValueError`` where ``what`` (a setting that starts new processes) meets a family
    that is neither built in nor installed (docs/install.md).
    """
    if not FAMILIES.installed(cfg.family):
        raise ValueError(
            f"{what} starts new processes, which find family {cfg.family!r} only if it is built "
            "in or installed (an entry point: docs/install.md); it was registered in this "
            "process only: install it, or set collector.num_workers=1"
        )


def make_env(
    cfg: Config,
    num_envs: int | None = None,
    seed: int | None = None,
    index_offset: int = 0,
    *,
    instances: Any = None,
    noise_seed: int | None = None,
    validate_actions: bool | None = None,
) -> EnvBase:
    """The family's batched env of ``cfg``: its training instances unless ``instances`` names
    another. ``index_offset``: global index of sub-environment 0 in the keyed streams.
    """
    return family(cfg).make_env(
        cfg,
        num_envs,
        seed=seed,
        index_offset=index_offset,
        instances=instances,
        noise_seed=noise_seed,
        validate_actions=validate_actions,
    )


def make_subtasks(cfg: Config, env: EnvBase) -> Subtasks:
    """The family's options (windy: one exit option per exit; Wargus: TG, FE, TG+FE)."""
    return family(cfg).subtasks(cfg, env)


def check_device(device: str | torch.device) -> None:
    """A one-line ``ValueError`` when ``device`` cannot be used by this torch build on this
    machine (e.g. ``device=cuda`` with a CPU-only torch)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError):
        raise ValueError(f"device must be cpu, cuda or cuda:N, got {str(device)!r}") from None
    if dev.type not in ("cpu", "cuda", "mps"):  # meta holds no data; xpu, hpu, lazy: untested
        raise ValueError(
            f"device={str(device)!r} cannot run taskvar_torch: use device=cpu"
            + (" or device=cuda" if torch.cuda.is_available() else "")
        )
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"device={str(device)!r} needs CUDA, which this torch {torch.__version__} cannot "
                "use here (CPU build or no GPU); use device=cpu"
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(
                f"device={str(device)!r}: this machine has {torch.cuda.device_count()} CUDA "
                "device(s); use device=cuda:0 or device=cpu"
            )
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device={str(device)!r} is not available here; use device=cpu")


# --------------------------------------------------------------------------------------------
# heads


@dataclass(frozen=True)
class HeadSpec:
    """The constructor arguments of a head bundle (a checkpoint's ``heads_spec``, so loading needs
    no env). Old checkpoints' ``informed_dim`` and ``informed_residual`` are ignored.
    """

    obs_dim: int
    num_actions: int
    option_names: tuple[str, ...]
    robustness: bool
    option_input_mask: tuple[tuple[float, ...], ...] | None = None

    @classmethod
    def of(cls, cfg: Config, env: EnvBase, subtasks: Subtasks) -> HeadSpec:
        """The spec of ``cfg``'s heads on ``env`` with ``subtasks``."""
        obs_dim = int(env.observation_spec[keys.OBSERVATION].shape[-1])
        mask = None
        if cfg.heads.option_inputs == "subtask":  # each option's policy sees its own features
            m = subtasks.option_input_mask(obs_dim)
            if m is None:
                raise ValueError(
                    f"heads.option_inputs='subtask': {type(subtasks).__name__} defines no option "
                    "inputs"
                )
            mask = tuple(tuple(float(v) for v in row) for row in m.tolist())
        return cls(
            obs_dim=obs_dim,
            num_actions=int(env.action_spec.space.n),
            option_names=tuple(subtasks.names),
            robustness=has_robustness(subtasks),
            option_input_mask=mask,
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a checkpoint (lists, not tuples)."""
        d = dataclasses.asdict(self)
        d["option_names"] = list(self.option_names)
        if self.option_input_mask is not None:
            d["option_input_mask"] = [list(r) for r in self.option_input_mask]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> HeadSpec:
        """The spec :meth:`to_dict` wrote; a missing field or a value of the wrong type or out of
        range is a one-line ``ValueError`` naming it (``heads_spec['obs_dim']``)."""
        check_heads_spec(d)
        mask = d.get("option_input_mask")
        return cls(
            obs_dim=int(d["obs_dim"]),
            num_actions=int(d["num_actions"]),
            option_names=tuple(d["option_names"]),
            robustness=bool(d["robustness"]),
            option_input_mask=None if mask is None else tuple(tuple(r) for r in mask),
        )


def check_heads_spec(d: Any) -> None:
    """A one-line ``ValueError`` naming the first ``heads_spec`` field that is missing, of the
    wrong type or out of range (what :class:`HeadSpec` builds networks from)."""

    def bad(key: str, what: str) -> ValueError:
        if key not in d:
            return ValueError(f"heads_spec has no {key!r} entry ({what})")
        return ValueError(f"heads_spec[{key!r}] must be {what}, got {d[key]!r}")

    if not isinstance(d, dict):
        raise ValueError(f"heads_spec must be a dict, got {type(d).__name__}")
    for key, high in (("obs_dim", 1 << 24), ("num_actions", 1 << 16)):
        v = d.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= high:
            raise bad(key, f"an integer in [1, {high}]")
    names = d.get("option_names")
    if not isinstance(names, (list, tuple)) or not 1 <= len(names) <= 1024:
        raise bad("option_names", "a list of 1 to 1024 names")
    if not all(isinstance(n, str) for n in names) or len(set(names)) != len(names):
        raise bad("option_names", "distinct strings")
    if not isinstance(d.get("robustness"), bool):
        raise bad("robustness", "true or false")
    mask = d.get("option_input_mask")
    if mask is not None and not (
        isinstance(mask, (list, tuple))
        and len(mask) == len(names)
        and all(
            isinstance(r, (list, tuple))
            and len(r) == d["obs_dim"]
            and all(type(v) in (int, float) for v in r)
            for r in mask
        )
    ):
        raise bad("option_input_mask", f"null or {len(names)} rows of {d['obs_dim']} numbers")


def build_heads(cfg: Config, env: EnvBase | HeadSpec, subtasks: Subtasks | None = None) -> Heads:
    """Fresh networks for every head the family needs, in a :class:`Heads` bundle (docs/design.md),
    as members of one ``StackedMLP`` (``StackedConvMLP`` with ``heads.network=conv``); ``env`` and
    ``subtasks`` give the :class:`HeadSpec`, or pass it.
    """
    spec = env if isinstance(env, HeadSpec) else HeadSpec.of(cfg, env, subtasks)
    A, O = spec.num_actions, len(spec.option_names)  # noqa: E741
    specs = {
        "averaging": (keys.ACTION_VALUE, (A,)),
        "options": (keys.OPTION_ACTION_VALUE, (O, A)),
        "switching": (keys.OPTION_VALUE, (O,)),
        "max_value": (keys.MAX_VALUE, (O,)),
    }
    if spec.robustness:
        specs["robustness"] = (keys.ROBUSTNESS, (O, A))
    fam = family(cfg)
    patch = fam.conv_patch(cfg) if cfg.heads.network == "conv" else None
    masks = None
    if spec.option_input_mask is not None:
        masks = {"options": torch.tensor(spec.option_input_mask, dtype=torch.float32)}
    heads = make_stacked_heads(
        spec.obs_dim,
        specs,
        hidden=tuple(cfg.heads.hidden),
        activation=cfg.heads.activation,
        network=cfg.heads.network,
        patch=patch,
        conv_channels=tuple(cfg.heads.conv_channels),
        input_masks=masks,
    )
    critic = None  # the instance estimator's C(s, o | z) (heads/max_value.py)
    if cfg.train.max_value_estimator == "instance":
        critic = make_instance_critic(
            spec.obs_dim, fam.instance_dim, O, tuple(cfg.heads.hidden), cfg.heads.activation
        )
    heads["max_value"] = TensorDictModule(  # Q_hat = Q_mu + softplus(gap) >= Q_mu
        OptimismGapHead(heads["switching"].module, heads["max_value"].module, critic),
        in_keys=[keys.OBSERVATION],
        out_keys=[keys.MAX_VALUE],
    )
    bundle = Heads(spec.option_names, **heads, softmax_temperature=mu_bar_temperature(cfg.train))
    bundle.spec = spec  # what a checkpoint records beside the weights (load_heads)
    return bundle.to(cfg.device)


def load_heads(
    path: str | os.PathLike,
    device: str | torch.device | None = None,
    controller: Sequence[str] = (),
) -> tuple[Heads, Config]:
    """The trained :class:`Heads` bundle and config of a checkpoint, built from its ``heads_spec``.

    ``controller``: controller settings (docs/controllers.md) applied to the bundle's config; an
    unknown key is a one-line ``ValueError``.

    Raises:
        CheckpointError: unreadable file, foreign content, non-finite heads, or weights that do not
            fit the config.
        ValueError: the bundle's device is not available here.
    """
    check_controller_overrides(controller)  # a one-line error before any loading
    return _heads_of(load_checkpoint(path), path, device, controller)


def _heads_of(
    bundle: dict[str, Any],
    path: str | os.PathLike,
    device: str | torch.device | None = None,
    controller: Sequence[str] = (),
) -> tuple[Heads, Config]:
    """The heads and config of a loaded checkpoint ``bundle`` (read from ``path``), with the
    ``controller`` settings applied to the config."""
    require_finite_heads(bundle, path)
    cfg = config_from_dict(bundle["config"], f"checkpoint {path}")
    cfg = with_controller_settings(cfg, controller)
    if cfg.train.seeds > 1:
        raise CheckpointError(
            f"{str(path)!r} holds a batch of {cfg.train.seeds} training runs (train.seeds): "
            f"evaluate one of them, {str(Path(path).parent / 'seed0' / 'final.pt')!r} ... "
            f"seed{cfg.train.seeds - 1}/final.pt"
        )
    if device is not None:
        cfg = dataclasses.replace(cfg, device=str(device))
    check_device(cfg.device)
    if isinstance(bundle.get("heads_spec"), dict):
        try:
            spec = HeadSpec.from_dict(bundle["heads_spec"])
        except ValueError as e:
            raise CheckpointError(f"checkpoint {str(path)!r} is corrupt: {e}") from None
        size = family(cfg).observation_size  # the config's own, where known without an env
        if size is not None and size(cfg) != spec.obs_dim:
            raise CheckpointError(
                f"checkpoint {str(path)!r} is corrupt: heads_spec['obs_dim'] is {spec.obs_dim} "
                f"but its config's observation has {size(cfg)} values"
            )
        # networks of the saved sizes: refused before allocating what the machine cannot hold
        check_memory(estimate_memory(cfg, training=False, obs_dim=spec.obs_dim))
    else:
        env = make_env(cfg, num_envs=1)
        spec = HeadSpec.of(cfg, env, make_subtasks(cfg, env))
    heads = build_heads(cfg, spec)
    key = evaluation_heads_key(bundle)
    models = bundle.get("models")
    if isinstance(models, dict) and isinstance(models.get(key), dict):
        # a checkpoint whose learner trained the informed head (removed; its own informed.pt
        # still evaluates): its tensors are not the paper's heads
        state = {k: v for k, v in models[key].items() if not k.startswith(OLD_INFORMED_PREFIX)}
        bundle = {**bundle, "models": {**models, key: state}}
    load_state_dicts(bundle, models={key: heads})
    return heads.eval(), cfg


OLD_INFORMED_PREFIX = "heads.informed."
"""State-dict prefix of the informed head older bundles hold (dropped on load)."""


HEADS_NAME = "heads.pt"
"""The shareable bundle ``taskvar train`` writes beside ``final.pt`` (:func:`export_heads`)."""


def export_heads(
    checkpoint: str | os.PathLike, out: str | os.PathLike | None = None, overwrite: bool = False
) -> Path:
    """Write a checkpoint's evaluation bundle (heads, ``heads_spec``, config; docs/evaluation.md) to
    ``out`` (default ``heads.pt`` beside it); an existing file is refused unless ``overwrite``.
    """
    dest = check_out_path(out) if out is not None else Path(checkpoint).with_name(HEADS_NAME)
    if dest.resolve() == Path(checkpoint).resolve():
        raise ValueError(f"--out {str(dest)!r} is the checkpoint itself; choose another --out")
    if dest.is_dir():
        raise ValueError(f"--out {str(dest)!r} is a folder; name the file to write")
    if dest.exists() and not overwrite:
        raise ValueError(f"{str(dest)!r} exists; pass --overwrite to replace it")
    if dest.exists() and is_training_checkpoint(dest):  # what a resume needs: never replaced
        raise ValueError(
            f"--out {str(dest)!r} is a training checkpoint (it resumes; heads.pt does not): "
            "choose another --out"
        )
    bundle = load_checkpoint(checkpoint)  # read once: a training checkpoint holds the replay
    heads, cfg = _heads_of(bundle, checkpoint)
    # not into a folder another taskvar command is writing
    with ResultsFolder(dest.parent, staged=False):
        return write_heads(dest, heads, cfg, counters=bundle.get("counters"))


def write_heads(
    path: str | os.PathLike, heads: Heads, cfg: Config, counters: dict | None = None
) -> Path:
    """Save ``heads`` (with their ``heads_spec``) and ``cfg`` as a shareable bundle at ``path``."""
    bundle = make_bundle(
        cfg,
        models={"heads": heads},
        counters=dict(counters or {}),
        rng={},
        heads_spec=heads.spec.to_dict(),
    )
    return save_checkpoint(path, bundle)


# --------------------------------------------------------------------------------------------
# learner


def make_learner(cfg: Config, heads: Heads, subtasks: Subtasks) -> MultiHeadLearner:
    """The fused multi-head learner of ``cfg.train``."""
    t = cfg.train
    if subtasks.given is not None and t.n_step > 1:
        given = [n for n, g in zip(subtasks.names, subtasks.given) if g]
        raise ValueError(
            f"train.n_step={t.n_step} with given-policy options ({', '.join(given)}): their "
            "n-step bootstrap is not supported yet; set train.n_step=1"
        )
    loss = MultiHeadLoss(heads, subtasks, t, family(cfg).instance_features)
    return MultiHeadLearner(
        loss.to(cfg.device),
        lr=t.lr,
        max_grad_norm=t.max_grad_norm,
        target_update=t.target_update,
        target_tau=t.target_tau,
        target_period=t.target_period,
        compile=t.compile,
        eval_ema_tau=t.eval_ema_tau,
    )


make_method = make_method_controller
"""Short name of :func:`make_method_controller`: the controller of a method (averaging, options,
interruption, hierarchy) on trained heads."""


__all__ = [
    "CALIBRATION_STATES",
    "HeadSpec",
    "build_heads",
    "calibrate",
    "check_device",
    "export_heads",
    "write_heads",
    "load_heads",
    "make_env",
    "make_learner",
    "make_method",
    "make_method_controller",
    "make_subtasks",
    "mu_bar_temperature",
    "replay_states",
    "training_states",
]
