"""Experiment evaluation layer: one-episode-per-env runner, pairing, statistics."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule

from taskvar_torch import keys
from taskvar_torch.experiments.evaluation import paired_summary, run_episodes
from taskvar_torch.families.windy import WindyGridEnv, WindyOracle

torch.set_num_threads(1)


def table_policy(policy_table: torch.Tensor) -> TensorDictModule:
    """Deterministic policy reading ``cell`` from an (S,) action table."""
    return TensorDictModule(
        lambda cell: policy_table[cell], in_keys=[keys.CELL], out_keys=[keys.ACTION]
    )


def test_run_episodes_mean_matches_oracle_expected_return():
    oracle = WindyOracle("default")
    pi = oracle.averaging_policy()
    out = run_episodes(WindyGridEnv(num_envs=20000, seed=3), table_policy(pi))
    exact = oracle.expected_return(pi, "train").item()
    se = out["return"].double().std().item() / 20000**0.5
    assert abs(out["return"].double().mean().item() - exact) < 4 * se
    assert (out["length"] == -out["return"]).all()  # -1 per step, one episode each


def test_same_seed_is_paired_and_noise_seed_is_not():
    oracle = WindyOracle("default")
    pol = table_policy(oracle.averaging_policy())
    a = run_episodes(WindyGridEnv(num_envs=4000, seed=1), pol)
    b = run_episodes(WindyGridEnv(num_envs=4000, seed=1), pol)
    c = run_episodes(WindyGridEnv(num_envs=4000, seed=1, noise_seed=7), pol)
    assert torch.equal(a["return"], b["return"])
    assert torch.equal(a["start"], c["start"]) and torch.equal(
        a["instance", "p"], c["instance", "p"]
    )
    s = paired_summary(c["return"] - a["return"])
    assert 0.0 < s["fraction_better"] < 1.0 and 0.0 < s["fraction_worse"] < 1.0
    assert abs(s["fraction_no_worse"] - (1 - s["fraction_worse"])) < 1e-12
    assert paired_summary(b["return"] - a["return"])["fraction_no_worse"] == 1.0
