"""Training the baselines beside a bundle: ``recurrent``, ``informed`` and ``blind``, each a DQN
agent of its own on its own epsilon-greedy stream (docs/memory.md#what-they-are).

They learn with TorchRL's pieces (``Collector``, ``EGreedyModule``, ``DQNLoss``, ``SoftUpdate`` /
``HardUpdate``, ``SliceSampler``, ``MultiStepTransform``) on the family's batched training env (a
new hidden instance at every reset, paper §2), and read every setting they share with the heads from
the config (:func:`baseline_train_config`). **recurrent**: DRQN over the observation, previous
action and reward, trained on slices from stored GRU states with a burn-in (R2D2). **informed**: a
plain MLP over ``[observation; instance features]``; **blind** the same with the features zeroed.
:func:`train_baseline` runs the heads' training loop
(:func:`~taskvar_torch.training.learning.collect_and_learn`) and writes ``DIR/<method>.pt``.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers import RandomSampler, SliceSampler
from torchrl.envs.transforms import MultiStepTransform
from torchrl.modules import EGreedyModule, GRUModule, set_recurrent_mode
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from taskvar_torch import keys
from taskvar_torch.config import Config, TrainConfig
from taskvar_torch.heads.informed import family_instance_keys, informed_features
from taskvar_torch.heads.recurrent import (
    BASELINES,
    PREV_ACTION,
    PREV_REWARD,
    RECURRENT_STATE,
    BaselineSpec,
    PreviousStep,
    baseline_path,
    make_informed_qnet,
    make_recurrent_qnet,
    save_baseline,
)
from taskvar_torch.progress import progress_bar
from taskvar_torch.training.collection import make_training_env
from taskvar_torch.training.learning import collect_and_learn, epsilon_at, learn_batch, non_finite

EPISODE_START = "episode_start"
"""Stored copy of ``is_init`` (a step that starts an episode): the sampler marks every slice start
as ``is_init``, and a slice that starts an episode needs no burn-in."""

_STORE = (
    keys.OBSERVATION,
    keys.ACTION,
    "is_init",
    (keys.NEXT, keys.OBSERVATION),
    (keys.NEXT, keys.REWARD),
    (keys.NEXT, keys.DONE),
    (keys.NEXT, keys.TERMINATED),
    (keys.NEXT, keys.TRUNCATED),
    (keys.NEXT, "is_init"),
)


def _check_method(method: str) -> None:
    if method not in BASELINES:
        raise ValueError(f"--method must be among {list(BASELINES)} or 'all', got {method!r}")


def build_for_training(cfg: Config, method: str) -> tuple[TensorDictSequential, BaselineSpec, Any]:
    """The network, its spec and the training env (with the recurrent head's transforms)."""
    _check_method(method)
    env = make_training_env(cfg)
    obs_dim = int(env.observation_spec[keys.OBSERVATION].shape[-1])
    num_actions = int(env.action_spec.space.n)
    act, mlp = cfg.heads.activation, tuple(cfg.heads.hidden)
    if method == "recurrent":
        hidden = int(cfg.baseline.hidden)
        net, gru = make_recurrent_qnet(obs_dim, num_actions, hidden, mlp, act)
        env.append_transform(PreviousStep(num_actions))
        env.append_transform(gru.make_tensordict_primer())
        spec = BaselineSpec(method, obs_dim, num_actions, mlp, hidden=hidden)
    else:  # informed, blind: the same network, blind's features zeroed
        dim, feats = informed_features(cfg)
        ikeys = family_instance_keys(cfg)
        blind = method == "blind"
        net = make_informed_qnet(obs_dim, num_actions, dim, feats, ikeys, mlp, act, blind=blind)
        spec = BaselineSpec(
            method, obs_dim, num_actions, mlp, instance_dim=dim, instance_keys=ikeys
        )
    return net.to(cfg.device), spec, env


def stored_keys(method: str) -> tuple:
    """What the replay keeps of each transition for ``method``: the step, plus the GRU's stored
    state and previous action and reward (``recurrent``) or the hidden instance at ``s`` and ``s'``
    and the agent's ``cell`` where the env has one (``informed``, ``blind``).
    """
    if method == "recurrent":
        prev = (PREV_ACTION, PREV_REWARD, (keys.NEXT, PREV_ACTION), (keys.NEXT, PREV_REWARD))
        return (*_STORE, RECURRENT_STATE, (keys.NEXT, RECURRENT_STATE), *prev)
    # the agent's cell too, where the env has one: egocentric features read it (MiniGrid's)
    return (*_STORE, keys.INSTANCE, (keys.NEXT, keys.INSTANCE), keys.CELL, (keys.NEXT, keys.CELL))


def heads_only_keys(cfg: Config, methods: tuple[str, ...] | list[str] = BASELINES) -> list[str]:
    """The ``train`` keys set away from their defaults that the baselines ``methods`` do not use
    (``replay_sampling``; ``n_step`` where ``recurrent`` is among them).
    """
    t = cfg.train
    out = []
    if t.n_step != 1 and "recurrent" in methods:
        out.append(f"train.n_step={t.n_step} (recurrent)")
    if t.replay_sampling != "uniform":
        out.append(f"train.replay_sampling={t.replay_sampling}")
    return out


def baseline_train_config(cfg: Config, method: str) -> TrainConfig:
    """The ``train`` settings ``method`` trains with: the heads', except a baseline's own frame
    budget where set (``baseline.recurrent_frames``, ``baseline.informed_frames``; epsilon and
    learning-rate decay scaled by the same factor) and ``baseline.informed_ema_tau`` as
    ``train.eval_ema_tau``.
    """
    t = cfg.train
    b = cfg.baseline
    frames = b.recurrent_frames if method == "recurrent" else b.informed_frames
    if method != "recurrent" and b.informed_ema_tau is not None:
        t = dataclasses.replace(t, eval_ema_tau=float(b.informed_ema_tau))
    if frames is None or int(frames) == int(t.total_frames):
        return t
    scale = int(frames) / max(int(t.total_frames), 1)
    return dataclasses.replace(
        t,
        total_frames=int(frames),
        eps_decay_frames=round(t.eps_decay_frames * scale),
        lr_decay_start_frames=round(t.lr_decay_start_frames * scale),
    )


def burn_in_mask(sample: TensorDictBase, burn_in: int) -> torch.Tensor:
    """``(R,)`` bool: the rows of a flat slice sample the recurrent loss is taken on (from the
    ``burn_in``-th row of each slice on, and every row of a slice that starts an episode).
    """
    starts = sample.get("is_init").reshape(-1)  # (R,) slice starts
    R = starts.shape[0]
    first = starts.nonzero().squeeze(-1)  # (num_slices,) each slice's first row
    slice_id = torch.cumsum(starts.long(), 0) - 1  # (R,)
    position = torch.arange(R, device=starts.device) - first[slice_id]  # (R,)
    from_start = sample.get(EPISODE_START).reshape(-1)[first][slice_id]  # (R,)
    return (position >= int(burn_in)) | from_start


LOSS_STATE = "recurrent_state_out"
"""Where the loss network's GRU writes the state it hands on (:func:`loss_network`)."""


def loss_network(net: TensorDictSequential) -> TensorDictSequential:
    """The recurrent Q-network as the loss runs it: the same modules and weights, its ``GRUModule``
    writing to :data:`LOSS_STATE`, so the next-state passes start each slice from the stored
    ``("next", "recurrent_state")`` (tests/test_recurrent_replay.py).
    """
    modules = []
    for m in net:
        if isinstance(m, GRUModule):
            m = GRUModule(
                gru=m.gru, in_keys=list(m.in_keys[:2]), out_keys=[m.out_keys[0], LOSS_STATE]
            )
        modules.append(m)
    return TensorDictSequential(*modules)


class BaselineLearner:
    """A baseline's replay and update rule: ``DQNLoss`` with a target network on ``net``, Adam,
    gradient clipping and the config's target update, all from ``cfg``.

    ``recurrent``: slices of ``baseline.burn_in + baseline.slice_len`` steps within episodes, the
    loss in ``set_recurrent_mode(True)`` from each slice's stored state past the burn-in;
    ``time_major`` (default) stores the collector's ``(N, T)`` batches as they come, else flat
    batches of whole contiguous episodes. Otherwise uniform transitions, with ``train.n_step``
    targets where above 1 (:meth:`store` holds the last ``n_step`` steps back until the next batch).
    """

    def __init__(
        self,
        net: TensorDictSequential,
        action_spec: Any,
        cfg: Config,
        recurrent: bool,
        time_major: bool = True,
    ):
        t = cfg.train
        self.cfg = cfg
        self.recurrent = recurrent
        self.time_major = time_major
        self.max_grad_norm = t.max_grad_norm
        self.burn_in = int(cfg.baseline.burn_in)
        self.loss = DQNLoss(
            loss_network(net) if recurrent else net,
            action_space=action_spec,
            delay_value=True,
            double_dqn=t.double_q,
            reduction="none",
        )
        self.loss.make_value_estimator(gamma=float(t.gamma))
        if t.target_update == "soft":
            self.updater = SoftUpdate(self.loss, tau=float(t.target_tau))
        else:  # TorchRL's HardUpdate copies every interval + 1 steps (heads/learner.py)
            self.updater = HardUpdate(self.loss, value_network_update_interval=t.target_period - 1)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(t.lr), foreach=True)
        self.updates_per_batch = int(t.updates_per_batch)
        self.device = next(net.parameters()).device
        self.net = net
        self.eval_net = net  # the weights evaluation reads (a Polyak average: train.eval_ema_tau)
        if t.eval_ema_tau is not None:
            self.eval_net = copy.deepcopy(net).requires_grad_(False)
            self._ema = list(self.eval_net.parameters())
            self._ema_source = list(net.parameters())
        if recurrent:
            length = self.burn_in + int(cfg.baseline.slice_len)
            slices = max(1, int(t.batch_size) // int(cfg.baseline.slice_len))
            self.buffer = TensorDictReplayBuffer(
                storage=LazyTensorStorage(int(t.buffer_size), ndim=2 if time_major else 1),
                sampler=SliceSampler(
                    slice_len=length, end_key=(keys.NEXT, keys.DONE), strict_length=False
                ),
                batch_size=slices * length,
                dim_extend=0,  # store() hands the time-major (T, N) view
            )
        else:
            self.buffer = TensorDictReplayBuffer(
                storage=LazyTensorStorage(int(t.buffer_size)),
                sampler=RandomSampler(),
                batch_size=int(t.batch_size),
            )
        self.multistep = None
        if not recurrent and int(t.n_step) > 1:
            # done_keys=[]: the done flags are taken at the step the target bootstraps from (TorchRL
            # leaves them at the first step by default, which would bootstrap past an episode's end)
            self.multistep = MultiStepTransform(int(t.n_step), float(t.gamma), done_keys=[])

    def store(self, batch: TensorDictBase) -> None:
        """Add a collector's batch (``(N, T)`` as ``T`` time rows for a ``time_major`` recurrent
        replay, else flat rows).
        """
        if self.recurrent:
            batch = batch.set(EPISODE_START, batch.get("is_init").clone())
            if self.time_major:
                # (N, T) -> (T, N), rows of the (time, sub-env) storage. Done here, not by
                # TorchRL (dim_extend=1), whose index bookkeeping fails when T = 1.
                batch = batch.transpose(0, 1)
        elif self.multistep is not None:
            batch = self.multistep.inv(batch)  # (N, T) -> (N, T'), T' = T minus the held-back steps
            if batch is None:  # fewer than n_step + 1 steps seen yet
                return
            batch = batch.reshape(-1)
        elif batch.ndim > 1:
            batch = batch.reshape(-1)
        self.buffer.extend(batch)

    def set_lr(self, lr: float) -> None:
        """The Adam learning rate from the next update on (the heads' schedule: ``lr_at``)."""
        for group in self.optim.param_groups:
            group["lr"] = lr

    def sample(self) -> TensorDictBase:
        """One replay sample: ``train.batch_size`` transitions, or (recurrent) the slices."""
        return self.buffer.sample()

    def slices(self, sample: TensorDictBase) -> torch.Tensor:
        """Ready a recurrent ``sample`` for the loss (each slice's first row marked ``("next",
        "is_init")``) and return its loss rows (:func:`burn_in_mask`).
        """
        nxt = (keys.NEXT, "is_init")
        sample.set(nxt, sample.get(nxt) | sample.get("is_init"))
        return burn_in_mask(sample, self.burn_in)

    def update(self, sample: TensorDictBase) -> torch.Tensor:
        """One gradient step on ``sample`` (:meth:`sample`); returns the loss (detached)."""
        sample = sample.to(self.device)
        if self.recurrent:
            mask = self.slices(sample).to(torch.float32)
            with set_recurrent_mode(True):
                per_row = self.loss(sample)["loss"].reshape(-1)
            value = (per_row * mask).sum() / mask.sum().clamp_min(1.0)
        else:
            value = self.loss(sample)["loss"].mean()
        self.optim.zero_grad(set_to_none=True)
        value.backward()
        if self.max_grad_norm is not None:
            params = self.loss.parameters()
            torch.nn.utils.clip_grad_norm_(params, float(self.max_grad_norm), foreach=True)
        self.optim.step()
        self.updater.step()
        if self.eval_net is not self.net:
            with torch.no_grad():
                torch._foreach_lerp_(
                    self._ema, self._ema_source, float(self.cfg.train.eval_ema_tau)
                )
        return value.detach()


@dataclasses.dataclass
class BaselineRun:
    """A baseline's training run between batches: learner, exploration, budget ``t``, frames and
    updates so far, and the returns of the episodes that ended in the last tenth of the budget.
    """

    method: str
    t: TrainConfig
    learner: BaselineLearner
    explore: EGreedyModule
    log: Callable[[str], None] | None = None
    counters: dict[str, int] = dataclasses.field(
        default_factory=lambda: {"frames": 0, "updates": 0}
    )
    returns: list[torch.Tensor] = dataclasses.field(default_factory=list)
    loss: torch.Tensor | None = None  # the last update's

    def store(self, batch: TensorDictBase) -> int:
        """Replay what the baseline keeps of ``batch`` (:func:`stored_keys`,
        :meth:`BaselineLearner.store`); returns the frame count before it."""
        before = self.counters["frames"]
        self.counters["frames"] += batch.numel()
        if self.counters["frames"] > 0.9 * int(self.t.total_frames):
            done = batch.get((keys.NEXT, keys.DONE)).squeeze(-1)
            self.returns.append(batch.get((keys.NEXT, "episode_reward")).squeeze(-1)[done])
        self.learner.store(batch.select(*stored_keys(self.method), strict=False))
        return before

    def learn(self) -> None:
        """The heads' learning step (:func:`~taskvar_torch.training.learning.learn_batch`) and epsilon
        (:func:`~taskvar_torch.training.learning.epsilon_at`) at the baseline's budget."""
        frames = self.counters["frames"]
        loss = learn_batch(
            self.learner, self.learner.sample, frames, len(self.learner.buffer), self.t
        )
        if loss is not None:
            self.loss = loss
            self.counters["updates"] += self.learner.updates_per_batch
        self.explore.eps.fill_(epsilon_at(frames, self.t))

    def report(self, frames_before: int) -> None:
        """A line to ``log`` about every 1000 updates."""
        frames, updates = self.counters["frames"], self.counters["updates"]
        if self.log is not None and updates and updates % 1000 < self.learner.updates_per_batch:
            self.log(
                f"{self.method}: {frames} frames, {updates} updates, loss {float(self.loss):.4f}"
            )


def train_baseline(
    cfg: Config,
    method: str,
    out_dir: str | os.PathLike,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Train the ``recurrent``, ``informed`` or ``blind`` baseline of ``cfg`` for its budget and
    write ``out_dir/<method>.pt``.

    Returns ``{"path", "frames", "budget", "updates", "seconds", "mean_train_return"}`` (the mean
    return of episodes ending in the last tenth of training, exploration included). Seeded by
    ``cfg.seed``.
    """
    t = baseline_train_config(cfg, method)
    torch.manual_seed(int(cfg.seed))
    net, spec, env = build_for_training(cfg, method)
    explore = EGreedyModule(env.action_spec, eps_init=1.0, eps_end=float(t.eps_end))
    learner = BaselineLearner(
        net, env.action_spec, dataclasses.replace(cfg, train=t), method == "recurrent"
    )
    run = BaselineRun(method, t, learner, explore, log)
    collector = Collector(
        env,
        TensorDictSequential(net, explore),
        frames_per_batch=int(t.frames_per_batch),
        total_frames=int(t.total_frames),
        track_traj_ids=False,
    )
    start = time.perf_counter()
    bar = progress_bar(total=int(t.total_frames), disable=not progress, desc=method, unit="frame")
    try:
        collect_and_learn(run, collector, bar, run.report)
    finally:
        bar.close()
        collector.shutdown()
    if non_finite({"weights": learner.eval_net.parameters()}):
        raise ValueError(f"the {method} baseline diverged (non-finite weights); nothing written")
    seconds = time.perf_counter() - start
    path = baseline_path(Path(out_dir) / "final.pt", method)
    frames, updates = run.counters["frames"], run.counters["updates"]
    counters = {"frames": frames, "budget": int(t.total_frames), "updates": updates}
    save_baseline(path, learner.eval_net, spec, cfg, counters={**counters, "seconds": seconds})
    rets = torch.cat(run.returns) if run.returns else torch.zeros(0)
    mean = float(rets.mean()) if rets.numel() else float("nan")
    return {"path": str(path), **counters, "seconds": seconds, "mean_train_return": mean}


__all__ = [
    "EPISODE_START",
    "BaselineLearner",
    "BaselineRun",
    "baseline_train_config",
    "build_for_training",
    "burn_in_mask",
    "heads_only_keys",
    "stored_keys",
    "train_baseline",
]
