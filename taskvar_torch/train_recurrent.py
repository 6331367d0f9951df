"""Training the baselines of issue 31 (docs/memory.md): ``recurrent`` and ``informed``.

Both learn with TorchRL's own pieces, on the family's batched training env (each sub-env draws a
new hidden instance at every reset, the distribution the paper's heads train on, §2) and with the
config's ``train.total_frames`` budget and epsilon schedule:

* a TorchRL :class:`~torchrl.collectors.Collector` over ``collection.make_training_env`` (plus, for the
  recurrent head, the previous action and the GRU's tensordict primer), acting epsilon-greedily
  (:class:`~torchrl.modules.EGreedyModule`, ``train.eps_start -> eps_end`` over
  ``train.eps_decay_frames`` after ``train.init_random_frames`` at ``eps_start``);
* ``DQNLoss(double_dqn=True, delay_value=True)`` (double Q with a target network) with
  ``SoftUpdate``, Adam and ``train.max_grad_norm`` clipping;
* recurrent: a replay of trajectories, ``LazyTensorStorage(ndim=2)`` holding each sub-env's
  stream along time (dim 0, so an episode cut by a batch boundary stays contiguous), sampled by :class:`~torchrl.data.replay_buffers.SliceSampler` in slices
  within episodes (``end_key = ("next", "done")``) that restart from the hidden state stored at
  collection (DRQN with stored state, as R2D2); the loss runs the GRU in
  ``set_recurrent_mode(True)``;
* informed: a replay of transitions sampled uniformly, the network reading the instance features.

:func:`train_baseline` writes ``DIR/recurrent.pt`` or ``DIR/informed.pt``
(``heads.recurrent.save_baseline``: atomic, plain data). Settings: ``BaselineSettings``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers import RandomSampler, SliceSampler
from torchrl.modules import EGreedyModule, set_recurrent_mode
from torchrl.objectives import DQNLoss, SoftUpdate

from taskvar_torch import keys
from taskvar_torch.collection import make_training_env
from taskvar_torch.config import Config
from taskvar_torch.heads.recurrent import (
    BASELINES,
    PREV_ACTION,
    RECURRENT_STATE,
    BaselineSettings,
    BaselineSpec,
    PreviousAction,
    baseline_path,
    family_instance_keys,
    informed_features,
    make_informed_qnet,
    make_recurrent_qnet,
    save_baseline,
)

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


def build_for_training(
    cfg: Config, method: str, settings: BaselineSettings
) -> tuple[TensorDictSequential, BaselineSpec, Any]:
    """The network, its spec and the training env (with the GRU primer for ``recurrent``)."""
    _check_method(method)
    env = make_training_env(cfg)
    obs_dim = int(env.observation_spec[keys.OBSERVATION].shape[-1])
    num_actions = int(env.action_spec.space.n)
    act = cfg.heads.activation
    if method == "recurrent":
        net, gru = make_recurrent_qnet(obs_dim, num_actions, settings, act)
        env.append_transform(PreviousAction(num_actions))
        env.append_transform(gru.make_tensordict_primer())
        spec = BaselineSpec(method, obs_dim, num_actions, settings)
    else:
        dim, feats = informed_features(cfg)
        ikeys = family_instance_keys(cfg)
        net = make_informed_qnet(obs_dim, num_actions, dim, feats, ikeys, settings, act)
        spec = BaselineSpec(method, obs_dim, num_actions, settings, dim, ikeys)
    return net.to(cfg.device), spec, env


def stored_keys(method: str) -> tuple:
    """What the replay keeps of each transition: the step (observation, action, next reward and
    done flags, episode starts) and, for ``recurrent``, the GRU's stored hidden state and the
    previous actions; for ``informed``, the hidden instance its features are read from."""
    if method == "recurrent":
        return (*_STORE, RECURRENT_STATE, PREV_ACTION, (keys.NEXT, PREV_ACTION))
    return (*_STORE, keys.INSTANCE, (keys.NEXT, keys.INSTANCE))


class BaselineLearner:
    """A baseline's replay and update rule: ``DQNLoss(double_dqn=True, delay_value=True)`` on
    ``net`` with ``SoftUpdate``, Adam and ``train.max_grad_norm`` clipping (module docstring).

    ``recurrent``: the replay holds trajectories, sampled by ``SliceSampler`` in slices of
    ``settings.slice_len`` within episodes (``end_key = ("next", "done")``) and the loss runs the
    GRU in ``set_recurrent_mode(True)``; ``time_major`` (the default) stores ``(time, sub-env)``
    batches (``LazyTensorStorage(ndim=2)``: an episode cut by a batch boundary stays contiguous),
    else flat batches whose episodes are already contiguous (the Figure 4 protocol's,
    ``experiments/fig4_recurrent.py``). Otherwise uniform transitions.
    """

    def __init__(
        self,
        net: TensorDictSequential,
        action_spec: Any,
        t: Any,
        settings: BaselineSettings,
        recurrent: bool,
        time_major: bool = True,
    ):
        self.recurrent = recurrent
        self.max_grad_norm = float(t.max_grad_norm)
        self.loss = DQNLoss(net, action_space=action_spec, delay_value=True, double_dqn=True)
        self.loss.make_value_estimator(gamma=float(t.gamma))
        self.updater = SoftUpdate(self.loss, tau=float(settings.target_tau or t.target_tau))
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(settings.lr or t.lr))
        self.updates_per_batch = int(settings.updates_per_batch or t.updates_per_batch)
        self.device = next(net.parameters()).device
        if recurrent:
            L = int(settings.slice_len)
            self.buffer = TensorDictReplayBuffer(
                storage=LazyTensorStorage(int(t.buffer_size), ndim=2 if time_major else 1),
                sampler=SliceSampler(
                    slice_len=L, end_key=(keys.NEXT, keys.DONE), strict_length=False
                ),
                batch_size=max(L, int(t.batch_size) // L * L),
            )
        else:
            self.buffer = TensorDictReplayBuffer(
                storage=LazyTensorStorage(int(t.buffer_size)),
                sampler=RandomSampler(),
                batch_size=int(t.batch_size),
            )

    def update(self) -> torch.Tensor:
        """One gradient step on one replay sample; returns the loss (detached)."""
        sample = self.buffer.sample().to(self.device)
        if self.recurrent:
            # slice starts are init steps for the next-state pass too (stored hidden state)
            nxt = (keys.NEXT, "is_init")
            sample.set(nxt, sample.get(nxt) | sample.get("is_init"))
            with set_recurrent_mode(True):
                value = self.loss(sample)["loss"]
        else:
            value = self.loss(sample)["loss"]
        self.optim.zero_grad(set_to_none=True)
        value.backward()
        torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.max_grad_norm)
        self.optim.step()
        self.updater.step()
        return value.detach()


def train_baseline(
    cfg: Config,
    method: str,
    out_dir: str | os.PathLike,
    settings: BaselineSettings | None = None,
    progress: bool = False,
    log: Any = None,
) -> dict[str, Any]:
    """Train the ``recurrent`` or ``informed`` baseline of ``cfg`` for ``train.total_frames``
    frames and write it to ``out_dir/<method>.pt``; returns ``{"path", "frames", "updates",
    "seconds", "mean_train_return"}`` (the mean return of the episodes that ended in the last
    tenth of training, exploration included).

    Seeded by ``cfg.seed`` (torch's global generator and the env's keyed streams)."""
    settings = settings or BaselineSettings()
    t = cfg.train
    torch.manual_seed(int(cfg.seed))
    net, spec, env = build_for_training(cfg, method, settings)
    recurrent = method == "recurrent"
    explore = EGreedyModule(
        env.action_spec,
        eps_init=float(t.eps_start),
        eps_end=float(t.eps_end),
        annealing_num_steps=max(1, int(t.eps_decay_frames)),
    )
    policy = TensorDictSequential(net, explore)
    learner = BaselineLearner(net, env.action_spec, t, settings, recurrent)
    store = stored_keys(method)
    collector = Collector(
        env,
        policy,
        frames_per_batch=int(t.frames_per_batch),
        total_frames=int(t.total_frames),
        track_traj_ids=False,
    )
    frames = updates = 0
    returns: list[torch.Tensor] = []
    start = time.perf_counter()
    bar = None
    if progress:
        from taskvar_torch.progress import progress_bar

        bar = progress_bar(total=int(t.total_frames), desc=method)
    for data in collector:
        n = data.numel()
        frames += n
        done = data.get((keys.NEXT, keys.DONE)).squeeze(-1)
        if frames > 0.9 * int(t.total_frames):
            returns.append(data.get((keys.NEXT, "episode_reward")).squeeze(-1)[done])
        batch = data.select(*store, strict=False)
        learner.buffer.extend(
            batch.transpose(0, 1).contiguous() if recurrent else batch.reshape(-1)
        )
        if frames >= int(t.init_random_frames):
            explore.step(n)
            for _ in range(learner.updates_per_batch):
                value = learner.update()
                updates += 1
            collector.update_policy_weights_()
        if bar is not None:
            bar.update(n)
        if log is not None and updates and updates % 1000 < learner.updates_per_batch:
            log(f"{method}: {frames} frames, {updates} updates, loss {float(value):.4f}")
    collector.shutdown()
    if bar is not None:
        bar.close()
    if not all(bool(p.isfinite().all()) for p in net.parameters()):
        raise ValueError(f"the {method} baseline diverged (non-finite weights); nothing written")
    seconds = time.perf_counter() - start
    path = baseline_path(Path(out_dir) / "final.pt", method)
    save_baseline(
        path, net, spec, cfg, counters={"frames": frames, "updates": updates, "seconds": seconds}
    )
    rets = torch.cat(returns) if returns else torch.zeros(0)
    return {
        "path": str(path),
        "frames": frames,
        "updates": updates,
        "seconds": seconds,
        "mean_train_return": float(rets.mean()) if rets.numel() else float("nan"),
    }


__all__ = ["BaselineLearner", "build_for_training", "stored_keys", "train_baseline"]
