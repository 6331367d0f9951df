"""Training with several collector processes (issue 6; ``collector.num_workers``): the workers'
envs are disjoint slices of the one-process env, and the learner's weights and epsilon reach the
workers after every update phase (TorchRL ``MultiSyncCollector`` + ``SharedMemWeightSyncScheme``)."""

from __future__ import annotations

import pytest
import torch

from taskvar_torch import keys
from taskvar_torch.checkpoint import CheckpointError, load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.heads.networks import head_network
from taskvar_torch.train import (
    build_heads,
    load_heads,
    make_subtasks,
    make_training_env,
    make_worker_env,
    train,
)

torch.set_num_threads(1)
CONFIG = "configs/windy.yaml"
SYNCED = 400  # the checkpoint at this frame holds the weights the workers act with next
BATCH = 100
TINY = [
    "env.num_envs=4",
    f"train.frames_per_batch={BATCH}",
    f"train.total_frames={SYNCED + BATCH}",
    f"train.checkpoint_every={SYNCED}",
    "train.log_every=100",
    "train.init_random_frames=200",
    "train.batch_size=32",
    "train.updates_per_batch=4",
    "train.lr=0.01",
    "train.buffer_size=1000",
    "train.first_visit=false",  # keep every transition, in collection order
    "train.option_behaviour_prob=0.0",  # every action from the averaging head...
    "train.eps_end=0.0",  # ...greedily once the random phase ends
    "train.eps_decay_frames=0",
    "collector.num_workers=2",
]


def test_worker_envs_are_disjoint_slices_of_the_one_process_env():
    cfg = load_config(CONFIG, ["env.num_envs=6", "train.frames_per_batch=60"])
    cfg3 = load_config(
        CONFIG, ["env.num_envs=6", "train.frames_per_batch=60", "collector.num_workers=3"]
    )
    whole = make_training_env(cfg).reset()
    parts, seeds = [], []
    with torch.random.fork_rng():  # make_worker_env seeds the worker's global RNG
        for w in range(3):
            parts.append(make_worker_env(cfg3, w))
            seeds.append(torch.initial_seed())
    assert len(set(seeds)) == 3, "every worker explores with its own RNG stream"
    sliced = torch.cat([env.reset() for env in parts], 0)
    for key in (keys.CELL, (keys.INSTANCE, "p"), (keys.INSTANCE, "direction")):
        assert torch.equal(sliced.get(key), whole.get(key)), key


def test_two_collector_processes_act_with_the_learners_latest_weights(tmp_path):
    cfg = load_config(CONFIG, TINY)
    threads = torch.get_num_threads()
    result = train(cfg, tmp_path / "run", progress=False)
    assert result["frames"] == SYNCED + BATCH and result["updates"] > 0
    assert torch.get_num_threads() == threads  # the collector's shutdown does not leak threads
    final = load_checkpoint(result["final"])
    assert final["env"] is None and final["carrier"] is None  # they live in the workers

    # The last batch was collected after the update phase that ended at frame SYNCED, whose
    # heads the checkpoint holds; epsilon was 0 then, so its actions are greedy in them.
    synced, _ = load_heads(tmp_path / "run" / f"checkpoint_{SYNCED:09d}.pt")
    replay = final["replay"]
    assert replay["size"] == SYNCED + BATCH
    obs = replay["data"][keys.OBSERVATION][-BATCH:]
    action = replay["data"][keys.ACTION][-BATCH:]

    def explained(heads) -> torch.Tensor:
        """Rows whose action is greedy in ``heads``' averaging head (up to rounding)."""
        with torch.no_grad():
            q = head_network(heads.heads["averaging"])(obs)
        return q.gather(-1, action.unsqueeze(-1)).squeeze(-1) >= q.max(-1).values - 1e-5

    assert explained(synced).all(), "the workers did not act with the learner's weights"
    # the check can fail: the untrained heads (the workers' weights without sync) do not explain it
    env = make_training_env(cfg, num_envs=2)
    torch.manual_seed(cfg.seed)
    fresh = build_heads(cfg, env, make_subtasks(cfg, env.base_env))
    assert not explained(fresh).all()

    with pytest.raises(CheckpointError, match="collector.num_workers=1"):
        train(None, tmp_path / "resumed", resume=result["final"], progress=False)
