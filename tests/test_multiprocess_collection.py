"""Training with several collector workers (``collector.num_workers``, ``collector.backend``):
the workers' envs are disjoint slices of the one-process env, and the learner's weights and epsilon
reach the workers after every update phase (TorchRL ``MultiSyncCollector`` +
``SharedMemWeightSyncScheme``; ``Collector(backend="ray")`` + ``RayWeightSyncScheme`` on a local Ray
with the test suite's 2 CPUs)."""

from __future__ import annotations

import sys

import pytest
import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.checkpoint import CheckpointError, load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, load_heads, make_subtasks
from taskvar_torch.heads.networks import head_network
from taskvar_torch.training import train
from taskvar_torch.training.collection import make_training_env, make_worker_env

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


try:
    import ray  # noqa: F401

    HAS_RAY = True
except ImportError:
    HAS_RAY = False
BACKENDS = ["process", pytest.param("ray", marks=pytest.mark.skipif(not HAS_RAY, reason="no Ray"))]


@pytest.fixture(scope="module")
def run_with(tmp_path_factory):
    """``run_with(backend)``: the TINY 2-worker training run on that collector backend (cached)."""
    runs: dict[str, tuple] = {}

    def run(backend: str):
        if backend not in runs:
            cfg = load_config(CONFIG, [*TINY, f"collector.backend={backend}"])
            threads = torch.get_num_threads()
            out = tmp_path_factory.mktemp(backend)
            result = train(cfg, out, progress=False)
            assert torch.get_num_threads() == threads  # shutdown does not leak threads
            runs[backend] = (cfg, out, result)
        return runs[backend]

    return run


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_two_collector_workers_act_with_the_learners_latest_weights(backend, run_with):
    cfg, out, result = run_with(backend)
    assert result["frames"] == SYNCED + BATCH and result["updates"] > 0
    final = load_checkpoint(result["final"])
    assert final["env"] is None and final["carrier"] is None  # they live in the workers

    # The last batch was collected after the update phase that ended at frame SYNCED, whose
    # heads the checkpoint holds; epsilon was 0 then, so its actions are greedy in them.
    synced, _ = load_heads(out / f"checkpoint_{SYNCED:09d}.pt")
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

    with pytest.raises(CheckpointError, match="collector.num_workers=1 and collector.backend"):
        train(None, out.parent / f"resumed-{backend}", resume=result["final"], progress=False)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_RAY, reason="no Ray")
def test_ray_actors_collect_exactly_what_the_worker_processes_collect(run_with):
    """Same slices, seeds and synced weights: Collector(backend="ray") on a local Ray gives the
    MultiSyncCollector run's transitions bit for bit, in the same (worker, env, time) order."""

    def replay(backend: str) -> TensorDict:
        state = load_checkpoint(run_with(backend)[2]["final"])["replay"]
        return TensorDict(state["data"], batch_size=[state["size"]])

    process, ray_ = replay("process"), replay("ray")
    assert process.shape == ray_.shape == (SYNCED + BATCH,)
    for key in (
        keys.OBSERVATION,
        keys.ACTION,
        (keys.NEXT, keys.OBSERVATION),
        (keys.NEXT, keys.DONE),
    ):
        assert torch.equal(process.get(key), ray_.get(key)), key


def test_ray_backend_without_ray_says_how_to_install_it(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    cfg = load_config(CONFIG, [*TINY, "collector.backend=ray"])
    with pytest.raises(ValueError, match=r'pip install "taskvar-torch\[distributed\]"'):
        train(cfg, tmp_path, progress=False)
