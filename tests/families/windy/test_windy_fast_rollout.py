"""``rollout_fast`` (benchmarks/reference/windy_fast_rollout.py, the reference loop the speed
benchmark times) gives TorchRL's ``Collector`` batches bit for bit, and the env's
speed-ups (batched reset draws, in-place hashing, direct state writes) keep its transitions."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.collectors import Collector

from taskvar_torch import rng
from taskvar_torch.families.windy import WindyGridEnv, WindyInstances, make_layout

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks" / "reference"))
from windy_fast_rollout import rollout_fast  # noqa: E402  (a reference loop, not the library)

CONFIGS = {
    "default": dict(num_envs=64, seed=3),
    "noise_fixed_start": dict(num_envs=50, seed=1, noise_seed=5, instances="south", start=(4, 0)),
    "large_patch": dict(
        num_envs=33,
        seed=2,
        layout=make_layout(9, 9, 3),
        obs_encoding="coords_patch",
        horizon=7,
        index_offset=10,
    ),
    "points": dict(
        num_envs=40, seed=4, instances={"points": [(0.3, "north"), (0.9, "south")]}, horizon=5
    ),
}


def _mostly_east(cell: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Deterministic and varied across sub-envs: east two times in three, so goals are reached."""
    k = (p * 997).long()
    return torch.where((cell * 31 + k) % 3 == 0, (cell + k) % 4, torch.full_like(cell, 2))


def _obs_policy(obs: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    return _mostly_east((obs * torch.arange(obs.shape[-1])).sum(-1).long(), p)


POLICIES = {
    "cell": TensorDictModule(_mostly_east, ["cell", ("instance", "p")], ["action"]),
    "observation": TensorDictModule(_obs_policy, ["observation", ("instance", "p")], ["action"]),
}


def _assert_same(ref, new):
    assert ref.batch_size == new.batch_size and ref.names == new.names
    assert set(ref.keys(True)) == set(new.keys(True))
    for key in ref.keys(True, True):
        a, b = ref.get(key), new.get(key)
        assert a.dtype == b.dtype and a.shape == b.shape, key
        assert torch.equal(a, b), key


@pytest.mark.parametrize("config", list(CONFIGS))
@pytest.mark.parametrize(
    "policy, compact, reuse",
    [("cell", False, False), ("cell", True, True), ("observation", False, True)],
)
def test_rollout_fast_equals_collector(config, policy, compact, reuse):
    cfg, pol, T = CONFIGS[config], POLICIES[policy], 12
    env_c, env_f = WindyGridEnv(**cfg), WindyGridEnv(**cfg)
    collector = Collector(
        env_c,
        pol,
        frames_per_batch=cfg["num_envs"] * T,
        total_frames=cfg["num_envs"] * T * 3,
        track_traj_ids=False,
        compact_obs=compact,
        auto_register_policy_transforms=False,
    )
    batch, ended = None, 0
    for ref in collector:
        batch = rollout_fast(env_f, pol, T, compact_obs=compact, out=batch if reuse else None)
        _assert_same(ref, batch)
        ended += int(ref["next", "done"].sum())
    collector.shutdown()
    assert ended > 0  # episodes ended and restarted inside the batches
    a, b = env_c.get_extra_state(), env_f.get_extra_state()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(torch.as_tensor(a[k]), torch.as_tensor(b[k])), k


def test_rollout_fast_stores_extra_policy_outputs_and_checks_out():
    class Policy(TensorDictModuleBase):
        in_keys = ["cell"]
        out_keys = ["action", "score"]

        def forward(self, td):
            td.set("action", td["cell"] % 4)
            return td.set("score", td["cell"].float().unsqueeze(-1) * 0.5)

    env = WindyGridEnv(num_envs=8, seed=0)
    batch = rollout_fast(env, Policy(), 5)
    assert batch["score"].shape == (8, 5, 1)
    assert torch.equal(batch["score"].squeeze(-1), batch["cell"].float() * 0.5)
    assert torch.equal(batch["action"], batch["cell"] % 4)
    with pytest.raises(ValueError, match="out has batch size"):
        rollout_fast(env, Policy(), 6, out=batch)
    with pytest.raises(ValueError, match="steps must be >= 1"):
        rollout_fast(env, Policy(), 0)


def test_reset_draws_equal_the_reference_draws():
    """The batched reset draws give what the one-counter-at-a-time reference functions give."""
    env = WindyGridEnv(num_envs=300, seed=7, instances=WindyInstances(0.2, 0.7, ("north", "east")))
    td = env.reset()
    key = rng.episode_key(rng.sub_env_key(7, torch.arange(300)), torch.zeros(300, dtype=torch.long))
    from taskvar_torch.families.windy.env import _C_START
    from taskvar_torch.families.windy.instances import _C_DIR, _C_P

    p = 0.2 + (0.7 - 0.2) * rng.draw_uniform(key, _C_P)
    direction = torch.tensor([0, 2])[rng.draw_index(key, _C_DIR, 2)]
    cell = env.model.start_cells[rng.draw_index(key, _C_START, env.model.start_cells.numel())]
    assert torch.equal(td["instance", "p"], p)
    assert torch.equal(td["instance", "direction"], direction)
    assert torch.equal(td["cell"], cell)
    assert torch.equal(env._key32, rng.to_i32(key))
    x = torch.randint(0, 2**32, (1000,))
    ref = x ^ (x >> 16)  # hash32's generic (out-of-place) steps
    ref = ((ref * rng._M1) & rng.MASK32) ^ (((ref * rng._M1) & rng.MASK32) >> 15)
    ref = (ref * rng._M2) & rng.MASK32
    assert torch.equal(rng.hash32(x), ref ^ (ref >> 16))
