"""The informed baseline (issue 31, docs/memory.md): the learnt ceiling reaches the exact
per-instance optimum, reads the family's instance features, is refused where a family has none
(Wargus's features: tests/families/wargus/test_informed_wargus.py),
and ``taskvar eval --method all`` plays both baselines on the same paired episodes."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest
import torch
from budgets import CORRIDOR_BUDGET  # tests/budgets.py
from torchrl.envs import TransformedEnv

from taskvar_torch import contract as families
from taskvar_torch.config import load_config
from taskvar_torch.experiments.bundle_eval import eval_bundle, format_table
from taskvar_torch.experiments.evaluation import mean_ci95, run_episodes
from taskvar_torch.factory import build_heads, make_env, make_subtasks, write_heads
from taskvar_torch.families.windy import WindyOracle
from taskvar_torch.heads.informed import INSTANCE_FEATURES, informed_features
from taskvar_torch.heads.recurrent import (
    BaselineSpec,
    InstanceFeatures,
    load_baseline,
    make_recurrent_qnet,
    save_baseline,
)
from taskvar_torch.oracle.episodes import optimal_episode_returns
from taskvar_torch.training.baselines import train_baseline

CORRIDOR = "configs/windy_corridor.yaml"
BOUND = 0.05
"""Stated bound on the informed head's mean regret against the exact per-instance optimum on the
corridor (measured: 0.003 +- 0.013 at 8192 frames, 4000 paired episodes)."""


@pytest.fixture(scope="module")
def corridor_informed(tmp_path_factory):
    torch.set_num_threads(1)
    cfg = load_config(CORRIDOR, CORRIDOR_BUDGET)
    out = tmp_path_factory.mktemp("informed")
    return cfg, out, train_baseline(cfg, "informed", out)


@pytest.mark.slow
def test_informed_within_bound_of_exact_optimum(corridor_informed):
    cfg, _, result = corridor_informed
    ctrl, _ = load_baseline(result["path"])
    env = TransformedEnv(make_env(cfg, 4000, seed=cfg.seed + 1), ctrl.primer())
    out = run_episodes(env, ctrl, max_steps=100)
    inst = {k: out["instance", k].numpy() for k in ("p", "direction")}
    optimum = optimal_episode_returns(WindyOracle(cfg.env.windy.layout), inst, out["start"].numpy())
    regret, ci = mean_ci95(torch.as_tensor(optimum) - out["return"].double())
    assert regret < BOUND, (regret, ci)
    assert regret > -3 * ci - 1e-9  # nothing beats the exact optimum beyond sampling noise


@pytest.mark.slow
def test_eval_all_plays_baselines_on_paired_episodes(corridor_informed, tmp_path):
    cfg, folder, _ = corridor_informed
    env = make_env(cfg, 1)
    write_heads(folder / "heads.pt", build_heads(cfg, env, make_subtasks(cfg, env)), cfg)
    net, _ = make_recurrent_qnet(5, 4, hidden=8, mlp=(8,))  # untrained: the mechanics, not merit
    spec = BaselineSpec("recurrent", 5, 4, (8,), hidden=8)
    save_baseline(folder / "recurrent.pt", net, spec, cfg)
    m = eval_bundle(folder / "heads.pt", "all", episodes=300, progress=False, out_dir=tmp_path)
    assert m["methods"][-2:] == ["recurrent", "informed"]
    point = m["points"][0]["methods"]
    for b in ("recurrent", "informed"):
        assert point[b]["regret_sampled"] is True and "exact_mean_return" not in point[b]
    assert point["informed"]["regret_mean"] < 0.2
    assert "not memoryless" in format_table(m)
    rows = list(csv.DictReader(open(tmp_path / "episodes.csv")))
    by = {}
    for r in rows:
        by.setdefault(r["method"], []).append(
            (r["instance_p"], r["instance_direction"], r["start"])
        )
    assert by["informed"] == by["averaging"] == by["recurrent"]  # the same episodes
    ret = {k: np.array([float(r["return"]) for r in rows if r["method"] == k]) for k in by}
    opt = np.array([float(r["optimum_return"]) for r in rows if r["method"] == "averaging"])
    assert float(np.mean(opt - ret["informed"])) == pytest.approx(point["informed"]["regret_mean"])


def test_instance_features_any_batch_shape():
    cfg = load_config(CORRIDOR, [])
    dim, feats = informed_features(cfg)
    mod = InstanceFeatures(feats, ("p", "direction"))
    env = make_env(cfg, 6, seed=3)
    td = env.rollout(4, break_when_any_done=False)  # (6, 4)
    out = mod(td)[INSTANCE_FEATURES]
    assert out.shape == (6, 4, dim)
    assert torch.equal(out[..., 0], td["instance", "p"])


def test_taxi_features_and_unavailable_without_any(monkeypatch):
    dim, feats = informed_features(load_config("configs/taxi.yaml", []))
    assert dim == 2  # rain and fickleness, not the episode's armed draw (docs/taxi.md)
    td = make_env(load_config("configs/taxi.yaml", ["env.instances=storm"]), 4, seed=0).reset()
    q, f = td["instance", "rainy_probability"], td["instance", "fickle_probability"]
    assert torch.equal(feats(td), torch.stack([1.0 - q, f], -1).float())
    assert (
        informed_features(load_config("configs/wargus.yaml", []))[0] == 4
    )  # tests/families/wargus/test_informed_wargus.py
    cfg = load_config("configs/wargus.yaml", [])
    monkeypatch.setattr(families, "family", _without_informed(families.family))
    with pytest.raises(ValueError, match="family 'wargus' has none, so it is unavailable") as e:
        informed_features(cfg)
    assert "\n" not in str(e.value)


def _without_informed(family):
    """``family`` with the informed hook removed: a family that gives no features at all."""
    return lambda c: dataclasses.replace(family(c), informed_features=None)
