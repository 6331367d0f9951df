"""Learner throughput, measured side by side in one run (docs/benchmarks.md).

(a) the multi-head learner (``MultiHeadLearner``): one buffer sample, one relabelling, one fused
    pass of every head (averaging, options, switching, max-value) stacked in one ``StackedMLP``,
    one backward, one fused Adam step, one foreach soft update;
(b) a naive loop: every head network its own TorchRL ``QValueActor`` + ``DQNLoss(double_dqn=True)``
    + Adam + ``SoftUpdate``, each with its own buffer sample and relabelled reward (averaging: env
    reward over 4 actions; one per option: subtask reward over 4 actions; switching and max-value:
    env reward over the 2 options).

Both train the same head networks (MLP width 64, two hidden layers) on the same windy replay data,
batch 256, single-threaded by default. One *update* trains every head once; samples/s counts the
transitions read. Runs alternate (a, b, a, b, ...) and the medians are compared, so a loaded
machine slows both alike. Target: (a) >= 1.5x (b).

Usage: ``python benchmarks/learner_throughput.py [--threads 1] [--seconds 3] [--repeats 3]
[--quick]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Categorical
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, make_learner, make_subtasks
from taskvar_torch.heads.behaviour import BehaviourPolicy
from taskvar_torch.heads.networks import make_mlp
from taskvar_torch.training.collection import make_training_env
from taskvar_torch.training.replay import make_replay_buffer, raw_transitions


def fill_buffer(cfg, frames: int):
    """A replay buffer of windy transitions from the exploring behaviour policy."""
    env = make_training_env(cfg)
    subtasks = make_subtasks(cfg, env.base_env)
    heads = build_heads(cfg, env, subtasks)
    buffer = make_replay_buffer(cfg, torch.Generator().manual_seed(0))
    policy = BehaviourPolicy(heads, subtasks, env.action_spec, option_prob=0.5)
    collector = Collector(
        env, policy, frames_per_batch=1024, total_frames=frames, track_traj_ids=False
    )
    for batch in collector:
        # as the trainer: the ``instance`` max-value estimator's critic reads the hidden instance
        buffer.extend(raw_transitions(batch, cfg.train.max_value_estimator == "instance"))
    collector.shutdown()
    return buffer, env, subtasks


class NaiveHead:
    """One head network trained alone: QValueActor + DQNLoss + Adam + SoftUpdate, own sample."""

    def __init__(self, obs_dim: int, n: int, reward_fn, done_fn, cfg):
        net = make_mlp(obs_dim, n, tuple(cfg.heads.hidden), cfg.heads.activation)
        spec = Categorical(n, shape=(), dtype=torch.int64)
        self.actor = QValueActor(net, in_keys=[keys.OBSERVATION], spec=spec)
        self.loss = DQNLoss(
            self.actor, action_space="categorical", delay_value=True, double_dqn=True
        )
        self.loss.make_value_estimator(gamma=cfg.train.gamma)
        self.opt = torch.optim.Adam(self.loss.parameters(), lr=cfg.train.lr)
        self.updater = SoftUpdate(self.loss, tau=cfg.train.target_tau)
        self.reward_fn, self.done_fn, self.n = reward_fn, done_fn, n

    def update(self, sample: TensorDict) -> torch.Tensor:
        td = TensorDict(
            {
                keys.OBSERVATION: sample[keys.OBSERVATION],
                keys.ACTION: sample[keys.ACTION] % self.n,
                keys.NEXT: {
                    keys.OBSERVATION: sample[keys.NEXT, keys.OBSERVATION],
                    keys.REWARD: self.reward_fn(sample).unsqueeze(-1),
                    keys.DONE: self.done_fn(sample).unsqueeze(-1),
                    keys.TERMINATED: self.done_fn(sample).unsqueeze(-1),
                },
            },
            batch_size=sample.batch_size,
        )
        loss = self.loss(td)["loss"]
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.updater.step()
        return loss.detach()


def naive_heads(cfg, env, subtasks) -> list[NaiveHead]:
    obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
    A, O = env.action_spec.space.n, subtasks.num_options  # noqa: E741

    def env_reward(s):
        return s[keys.NEXT, keys.REWARD].reshape(-1)

    def env_done(s):
        return s[keys.NEXT, keys.TERMINATED].reshape(-1)

    def option_reward(o):
        return lambda s: subtasks.reward(s)[:, o]

    def option_done(o):
        return lambda s: subtasks.termination(s[keys.NEXT])[:, o] | env_done(s)

    heads = [NaiveHead(obs_dim, A, env_reward, env_done, cfg)]
    heads += [NaiveHead(obs_dim, A, option_reward(o), option_done(o), cfg) for o in range(O)]
    heads += [NaiveHead(obs_dim, O, env_reward, env_done, cfg) for _ in ("switching", "max_value")]
    return heads


def timed(step, seconds: float) -> float:
    """Updates per second of ``step`` over about ``seconds`` (after a warm-up)."""
    for _ in range(5):
        step()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        step()
        n += 1
    return n / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=3.0, help="per timed run")
    parser.add_argument("--repeats", type=int, default=3, help="alternating runs of each")
    parser.add_argument("--frames", type=int, default=20_480, help="replay transitions")
    parser.add_argument(
        "--quick", action="store_true", help="2k transitions, one 0.2 s run each (smoke run)"
    )
    args = parser.parse_args()
    if args.quick:
        args.seconds, args.repeats, args.frames = 0.2, 1, 2048
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    cfg = load_config("configs/windy.yaml", ["train.batch_size=256", "heads.hidden=[64,64]"])
    B = cfg.train.batch_size
    buffer, env, subtasks = fill_buffer(cfg, args.frames)

    heads = build_heads(cfg, env, subtasks)
    learner = make_learner(cfg, heads, subtasks)
    naive = naive_heads(cfg, env, subtasks)
    print(
        f"threads={torch.get_num_threads()} batch={B} hidden={list(cfg.heads.hidden)} "
        f"replay={len(buffer)} transitions; heads: averaging, {subtasks.num_options} options, "
        "switching, max-value"
    )

    def fused_step():
        learner.update(buffer.sample())

    def naive_step():
        for h in naive:
            h.update(buffer.sample())

    fused, slow = [], []
    for _ in range(args.repeats):
        fused.append(timed(fused_step, args.seconds))
        slow.append(timed(naive_step, args.seconds))
    a, b = statistics.median(fused), statistics.median(slow)
    k = len(naive)
    print(f"(a) multi-head learner : {a:8.1f} updates/s  {a * B:10.0f} samples/s  (all heads)")
    print(f"(b) naive DQNLoss loop : {b:8.1f} updates/s  {b * B * k:10.0f} samples/s  ({k} losses)")
    print(f"    head-updates/s     : (a) {a * k:8.1f}   (b) {b * k:8.1f}")
    print(f"ratio (a)/(b) updates/s: {a / b:.2f}x  (target >= 1.5x)")


if __name__ == "__main__":
    main()
