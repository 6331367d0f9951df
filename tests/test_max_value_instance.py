"""The ``instance`` max-value estimator (Definition 1: a max over instances of per-instance values).

Unit checks of ``heads/max_value.py::instance_max_value_loss`` and of its plumbing (config, replay,
checkpoint); the learning check against the exact oracle is in ``tests/families/windy/test_heads_windy.py``.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from taskvar_torch import keys
from taskvar_torch.config import TrainConfig, load_config
from taskvar_torch.factory import build_heads, load_heads, make_env, make_subtasks
from taskvar_torch.families.windy.family import WINDY_INSTANCE_DIM
from taskvar_torch.families.windy.family import windy_instance_features as instance_features
from taskvar_torch.heads.learner import MultiHeadLoss
from taskvar_torch.heads.max_value import (
    OptimismGapHead,
    distinct_rows,
    instance_max,
    instance_max_value_loss,
    make_instance_critic,
)
from taskvar_torch.heads.networks import head_network
from taskvar_torch.heads.relabel import relabel
from taskvar_torch.training import train

torch.set_num_threads(1)
INSTANCE = ["train.max_value_estimator=instance", "env.num_envs=4"]


@pytest.fixture(scope="module")
def windy():
    cfg = load_config("configs/windy.yaml", INSTANCE)
    env = make_env(cfg)
    subtasks = make_subtasks(cfg, env)
    return cfg, env, subtasks


def batch_with_instances(env, B: int = 64) -> TensorDict:
    """B raw transitions of random actions, the hidden instance kept (as the replay keeps it)."""
    td = env.rollout(B // env.num_envs + 30, break_when_any_done=False).reshape(-1)
    return td[torch.randperm(td.shape[0], generator=torch.Generator().manual_seed(0))[:B]].exclude(
        (keys.NEXT, keys.INSTANCE)
    )


class ReadP(nn.Module):
    """A fake critic ``C(s, o | z) = p`` for every option (the instance's gust probability)."""

    def __init__(self, num_options: int):
        super().__init__()
        self.num_options = num_options

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = x[..., -WINDY_INSTANCE_DIM]  # (...,)
        return p.unsqueeze(-1).expand(*p.shape, self.num_options)


def test_instance_features_are_p_and_one_hot_direction(windy):
    _, env, _ = windy
    td = batch_with_instances(env)
    z = instance_features(td)  # (B, 5)
    assert z.shape == (td.shape[0], WINDY_INSTANCE_DIM)
    assert torch.equal(z[:, 0], td.get((keys.INSTANCE, "p")))
    assert torch.equal(z[:, 1:].argmax(-1), td.get((keys.INSTANCE, "direction")))
    assert instance_features(td.exclude(keys.INSTANCE)) is None


def test_head_target_is_the_max_over_the_samples_instances(windy):
    _, env, subtasks = windy
    batch = relabel(batch_with_instances(env), subtasks, instance_features=instance_features)
    B, O = batch.initiation.shape  # noqa: E741
    critic = ReadP(O)
    mu = torch.full((B, O), 1.0 / O)
    consistent = torch.ones(B, O, dtype=torch.bool)
    for m in (1, 8, B):
        best = batch.instance[:m, 0].max()  # max over the first m instances of C = p
        at_max = best.expand(B, O).clone()
        _, loss_hat = instance_max_value_loss(
            at_max, critic, critic, mu, consistent, batch, 0.99, m
        )
        assert float(loss_hat) == pytest.approx(0.0, abs=1e-12)
        _, off = instance_max_value_loss(
            at_max - 1.0, critic, critic, mu, consistent, batch, 0.99, m
        )
        assert float(off) > 0.5  # one unit off on every initiable (s, o), summed over O options


def test_critic_target_bootstraps_in_the_transitions_own_instance(windy):
    _, env, subtasks = windy
    batch = relabel(batch_with_instances(env), subtasks, instance_features=instance_features)
    B, O = batch.initiation.shape  # noqa: E741
    critic = ReadP(O)
    mu = torch.full((B, O), 1.0 / O)
    consistent = torch.ones(B, O, dtype=torch.bool)
    q_hat = torch.zeros(B, O)
    loss_c, _ = instance_max_value_loss(q_hat, critic, critic, mu, consistent, batch, 0.5)
    p = batch.instance[:, :1]  # (B, 1): C = p at s and at s', the same instance
    y = batch.reward.unsqueeze(-1) + 0.5 * (1.0 - batch.terminated).unsqueeze(-1) * p
    want = O * (p - y).pow(2).mean()  # every pair consistent: mean over B, sum over O
    assert float(loss_c) == pytest.approx(float(want), rel=1e-6)


def test_critic_loss_trains_the_critic_and_head_loss_only_the_gap(windy):
    cfg, env, subtasks = windy
    torch.manual_seed(0)
    heads = build_heads(cfg, env, subtasks)
    net = head_network(heads.heads["max_value"])
    assert isinstance(net, OptimismGapHead) and net.critic is not None
    loss = MultiHeadLoss(
        heads, subtasks, TrainConfig(max_value_estimator="instance"), instance_features
    )
    td = batch_with_instances(env)
    batch = relabel(td, subtasks, instance_features=instance_features)
    cur, *_ = loss._head_outputs(batch.observation, batch.next_observation)
    B, O = batch.initiation.shape  # noqa: E741
    mu = torch.full((B, O), 1.0 / O)
    consistent = torch.ones(B, O, dtype=torch.bool)
    target_critic = head_network(loss.target_heads["max_value"]).critic
    loss_c, loss_hat = instance_max_value_loss(
        cur["max_value"], net.critic, target_critic, mu, consistent, batch, 0.99
    )
    stack = head_network(heads.heads["averaging"]).stack
    heads.zero_grad()
    loss_c.backward(retain_graph=True)
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.critic.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in stack.parameters())
    heads.zero_grad()
    loss_hat.backward()
    g = stack.weights[0].grad  # (K, D, H)
    assert [j for j in range(g.shape[0]) if g[j].abs().sum() > 0] == [net.gap.index]
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in net.critic.parameters())
    # the learner logs one max-value entry (critic + distillation), as the expectile one
    assert set(loss(td).keys()) == {
        "loss_averaging",
        "loss_options",
        "loss_switching",
        "loss_max_value",
    }


def test_instance_estimator_needs_instances_and_a_critic(windy):
    cfg, env, subtasks = windy
    batch = batch_with_instances(env).exclude(keys.INSTANCE)
    heads = build_heads(cfg, env, subtasks)
    loss = MultiHeadLoss(
        heads, subtasks, TrainConfig(max_value_estimator="instance"), instance_features
    )
    with pytest.raises(ValueError, match="hidden instance"):
        loss(batch)
    expectile = ["env.num_envs=4", "train.max_value_estimator=expectile"]
    plain = build_heads(load_config("configs/windy.yaml", expectile), env, subtasks)
    with pytest.raises(ValueError, match="instance critic"):
        MultiHeadLoss(plain, subtasks, TrainConfig(max_value_estimator="instance"))
    with pytest.raises(ValueError, match="max_value_estimator"):
        MultiHeadLoss(heads, subtasks, TrainConfig(max_value_estimator="mc"))


def test_config_rejects_the_instance_estimator_without_instance_features():
    with pytest.raises(ValueError, match="train.max_value_estimator"):
        load_config("configs/windy.yaml", ["train.max_value_estimator=max"])
    with pytest.raises(ValueError, match="family='windy'"):
        load_config("configs/wargus.yaml", ["train.max_value_estimator=instance"])


@pytest.mark.slow
def test_a_fresh_instance_checkpoint_loads_with_its_critic(tmp_path):
    cfg = load_config(
        "configs/windy.yaml",
        INSTANCE
        + [
            "train.total_frames=2048",
            "train.init_random_frames=512",
            "train.checkpoint_every=0",
            "train.updates_per_batch=2",
        ],
    )
    result = train(cfg, tmp_path, progress=False)
    assert result["updates"] > 0 and "loss_max_value" in result["last_log"]
    heads, loaded = load_heads(result["final"])
    assert loaded.train.max_value_estimator == "instance"
    assert head_network(heads.heads["max_value"]).critic is not None
    td = heads(TensorDict({keys.OBSERVATION: torch.eye(25)}, [25]))
    assert (td[keys.MAX_VALUE] >= td[keys.OPTION_VALUE]).all()


@pytest.mark.parametrize("seeds", [1, 3])
def test_grid_on_distinct_states_is_the_grid_on_every_row(seeds):
    # the max over Z evaluated once per distinct observation and gathered: the same bits as the
    # (B, M) grid of every row (the CPU shortcut of heads/max_value.py instance_max)
    torch.manual_seed(0)
    critic = make_instance_critic(25, WINDY_INSTANCE_DIM, 2)
    B = 96 * seeds
    obs = torch.nn.functional.one_hot(torch.randint(0, 25, (B,)), 25).float()
    direction = torch.nn.functional.one_hot(torch.randint(0, 4, (B,)), 4).float()
    z = torch.cat([torch.rand(B, 1), direction], -1)
    distinct = distinct_rows(obs, seeds)
    assert distinct is not None
    rows, index = distinct
    assert torch.equal(rows[index], obs) and rows.shape[0] < B
    zs = z.view(seeds, -1, z.shape[-1])[:, :64]  # (S, M, F)
    grid_z = zs.unsqueeze(1).expand(seeds, B // seeds, 64, -1).reshape(B, 64, -1)
    grid = torch.cat([obs.unsqueeze(1).expand(B, 64, -1), grid_z], -1)
    with torch.no_grad():
        every_row = critic(grid).max(1).values
        assert torch.equal(instance_max(critic, obs, z, seeds, 64), every_row)


def test_distinct_rows_falls_back_where_keys_collide(monkeypatch):
    x = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    rows, index = distinct_rows(x)
    assert rows.shape[0] == 2 and torch.equal(rows[index], x)
    monkeypatch.setattr(torch, "unique", lambda k, **kw: (k[:1], torch.zeros_like(k, dtype=int)))
    assert distinct_rows(x) is None  # two distinct rows under one key: no shortcut
