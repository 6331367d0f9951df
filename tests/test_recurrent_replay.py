"""The recurrent baseline's replay holds real trajectories: every sampled slice is consecutive
steps of one sub-env, inside one episode, and a sample has the slices and rows asked for, a slice
cut short only by its episode's end or the newest step stored (docs/memory.md; the defect it
guards against stored each batch transposed, so slices ran across sub-envs).

The check tags every collected step with its sub-env and its step in the episode (TorchRL's
``StepCounter``), stores the collector's batches through the learner's own ``store``, and reads the
tags back from samples."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs import StepCounter
from torchrl.modules import EGreedyModule

from taskvar_torch.config import load_config
from taskvar_torch.training.baselines import (
    EPISODE_START,
    BaselineLearner,
    build_for_training,
    burn_in_mask,
    stored_keys,
)

SMALL = ["train.total_frames=100000", "train.buffer_size=20000"]


def _filled_learner(config: str, batches: int, overrides=()):
    cfg = load_config(config, [*SMALL, *overrides])
    torch.manual_seed(0)
    net, _, env = build_for_training(cfg, "recurrent")
    env.append_transform(StepCounter())
    policy = TensorDictSequential(net, EGreedyModule(env.action_spec, eps_init=1.0, eps_end=1.0))
    learner = BaselineLearner(net, env.action_spec, cfg, recurrent=True)
    fpb = int(cfg.train.frames_per_batch)
    collector = Collector(env, policy, frames_per_batch=fpb, total_frames=fpb * batches)
    tags = ("env_index", "step_count", ("next", "step_count"))
    for data in collector:
        n = data.shape[0]
        data.set("env_index", torch.arange(n).view(n, 1).expand(data.shape).clone())
        learner.store(data.select(*stored_keys("recurrent"), *tags))
    collector.shutdown()
    newest = data["step_count"][:, -1].reshape(-1)  # (N,) each sub-env's newest stored step
    return cfg, learner, newest


@pytest.mark.parametrize(
    "config,batches,overrides",
    [
        ("configs/taxi.yaml", 30, []),
        pytest.param("configs/windy.yaml", 40, [], marks=pytest.mark.slow),  # ~3 s: make test
        ("configs/wargus.yaml", 4, []),
        # one step per sub-env a batch, as the scale experiment's cells collect ((N, 1) batches)
        pytest.param(
            "configs/windy.yaml",
            400,
            ["env.num_envs=16", "train.frames_per_batch=16"],
            marks=pytest.mark.slow,
        ),
    ],
)
def test_sampled_slices_are_one_sub_env_trajectories(config, batches, overrides):
    cfg, learner, newest = _filled_learner(config, batches, ["train.compile=false", *overrides])
    length = cfg.baseline.burn_in + cfg.baseline.slice_len
    slices = max(1, cfg.train.batch_size // cfg.baseline.slice_len)
    assert learner.buffer.batch_size == slices * length
    for _ in range(20):
        s = learner.buffer.sample()
        starts = s["is_init"].reshape(-1)
        assert bool(starts[0]) and int(starts.sum()) == slices  # the slices asked for
        env_index, step = s["env_index"].reshape(-1), s["step_count"].reshape(-1)
        done = s["next", "done"].reshape(-1)
        inner = ~starts[1:]  # consecutive rows of one slice
        assert torch.equal(env_index[1:][inner], env_index[:-1][inner])  # one sub-env
        assert torch.equal(step[1:][inner], step[:-1][inner] + 1)  # consecutive, no reset inside
        assert not bool(done[:-1][inner].any())  # an episode ends only at a slice's last row
        slice_id = torch.cumsum(starts.long(), 0) - 1
        sizes = torch.bincount(slice_id)
        assert int(sizes.max()) <= length
        # the rows asked for: a slice is short only where its episode ended or the stream does
        last = torch.cumsum(sizes, 0) - 1
        short = sizes < length
        at_end = done[last] | (step[last] == newest[env_index[last]])
        assert bool(at_end[short].all()), (sizes[short], done[last][short])
        # a slice that starts an episode starts it at step 0 (StepCounter counts from 0)
        first = starts.nonzero().squeeze(-1)
        from_start = s[EPISODE_START].reshape(-1)[first]
        assert bool((step[first][from_start] == 0).all())


def test_burn_in_mask_skips_the_warm_up_unless_the_slice_starts_an_episode():
    from tensordict import TensorDict

    # two slices of 5 rows: the first starts mid-episode, the second at an episode's start
    is_init = torch.tensor([1, 0, 0, 0, 0, 1, 0, 0, 0, 0], dtype=torch.bool)
    start = torch.tensor([0, 0, 0, 0, 0, 1, 0, 0, 0, 0], dtype=torch.bool)
    td = TensorDict({"is_init": is_init[:, None], EPISODE_START: start[:, None]}, [10])
    mask = burn_in_mask(td, 2)
    expected = torch.tensor([0, 0, 1, 1, 1, 1, 1, 1, 1, 1], dtype=torch.bool)
    assert torch.equal(mask, expected)
    assert bool(burn_in_mask(td, 0).all())


@pytest.mark.parametrize(
    "config,batches",
    [pytest.param("configs/windy.yaml", 40, marks=pytest.mark.slow), ("configs/taxi.yaml", 30)],
)
def test_both_passes_start_a_slice_from_the_stored_state(config, batches):
    """With the weights of collection, the next-state pass at row j of a slice gives the online
    pass's Q-values at row j + 1: both start from the stored GRU state (a next-state pass started
    from zeros differs at every slice that does not start an episode). Checked on the network and
    through the loss itself: ``DQNLoss``'s per-row loss is the squared TD error against the double-Q
    target from the stored-state next pass (target weights = online ones before any update)."""
    from torchrl.modules import set_recurrent_mode

    cfg, learner, _ = _filled_learner(config, batches, ["train.compile=false"])
    net = learner.net
    assert cfg.train.double_q
    checked = 0
    for _ in range(5):
        s = learner.buffer.sample()
        learner.slices(s)
        starts = s["is_init"].reshape(-1)
        with torch.no_grad(), set_recurrent_mode(True):
            online = net(s.clone())["action_value"]
            nxt = net(s["next"].clone())["action_value"]
            loss = learner.loss(s.clone())["loss"].reshape(-1)
        inner = ~starts[1:]
        torch.testing.assert_close(nxt[:-1][inner], online[1:][inner], atol=1e-5, rtol=1e-5)
        # the loss: (Q(s, a) - r - gamma (1 - terminated) Q(s', argmax Q(s', .)))^2 per row
        pred = online.gather(-1, s["action"].long().reshape(-1, 1)).reshape(-1)
        bootstrap = nxt.gather(-1, nxt.argmax(-1, keepdim=True)).reshape(-1)
        alive = (~s["next", "terminated"].reshape(-1)).float()
        target = s["next", "reward"].reshape(-1) + cfg.train.gamma * alive * bootstrap
        torch.testing.assert_close(loss, (pred - target) ** 2, atol=1e-5, rtol=1e-4)
        # the rows that test the slice's start: its first row, where the slice is mid-episode
        first = starts.nonzero().squeeze(-1)
        mid = ~s[EPISODE_START].reshape(-1)[first]
        checked += int((mid & inner[first.clamp_max(len(inner) - 1)]).sum())
    assert checked > 0
