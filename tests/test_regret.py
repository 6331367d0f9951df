"""Regret against the exact per-instance optimum (issue 31, item 3; docs/evaluation.md): the
oracles' ``optimal_return`` (windy and Taxi, one interface), ``optimal_episode_returns`` and the
``regret_*`` keys, ``optimum_return`` column and ``regret`` table column of ``taskvar eval``."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.experiments.bundle_eval import eval_bundle, format_table, point_oracle
from taskvar_torch.experiments.shift import shift_points
from taskvar_torch.factory import make_method_controller
from taskvar_torch.families.taxi.oracle import TaxiOracle
from taskvar_torch.families.taxi.subtasks import TaxiSubtasks
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.oracle import WindyOracle
from taskvar_torch.oracle.episodes import exact_episode_returns, optimal_episode_returns
from taskvar_torch.oracle.mdp import greedy

torch.set_num_threads(1)


@pytest.mark.parametrize("layout", ["default", "whole_column_windy"])
def test_the_windy_optimum_bounds_every_controller_exactly(layout):
    oracle = WindyOracle(layout, train_instances="south" if layout != "default" else "train")
    g = torch.Generator().manual_seed(0)
    p = torch.rand(64, generator=g, dtype=torch.float64)
    d = torch.randint(0, 2, (64,), generator=g)
    best = oracle.optimal_return(p, d)  # (B, S)
    assert best.shape == (64, oracle.S)
    P, R = windy.transition_tensors(oracle.model, p[:8], d[:8])  # dense backward induction
    V = torch.zeros(8, oracle.S, dtype=torch.float64)
    for _ in range(oracle.horizon):
        V = (R + torch.einsum("bsat,bt->bsa", P, V)).max(-1).values
    assert torch.allclose(best[:8], V, atol=1e-12, rtol=0)
    for name in ("averaging", "options", "interruption"):
        assert float((best - oracle.controller_return(name, p, d)).min()) >= -1e-9, name
    greedy_pi = greedy(oracle.optimal_q(p, d))  # the discounted-optimal stationary policy
    for b in range(4):
        ret = oracle.episode_return(greedy_pi[b], p[b], int(d[b]))
        assert float((best[b] - ret).min()) >= -1e-9
    assert float(oracle.optimal_return(0.3, "north", start=(0, 0))) < 0


@pytest.mark.slow
def test_taxi_regret_with_the_oracles_own_heads_on_fickle():
    """docs/taxi.md: on `fickle` interruption 9.280 = the optimum 9.280, options 2.080 (regret
    7.2). Every Taxi-v4 start at E f = 0.9 (dry: returns affine in f there, so exact)."""
    oracle = TaxiOracle(horizon=200)
    cfg = load_config("configs/taxi.yaml")
    starts = oracle.start_cells.numpy()
    inst = {
        "rainy_probability": np.ones(starts.size, np.float32),
        "fickle_probability": np.full(starts.size, 0.9, np.float32),
    }
    best = optimal_episode_returns(oracle, inst, starts)
    assert abs(best.mean() - 9.280) < 5e-4
    heads = oracle.heads(keys.OBSERVATION, dtype=torch.float32)
    regret = {}
    for m in ("options", "interruption"):
        ctrl = make_method_controller(cfg, m, heads, TaxiSubtasks())
        exact = exact_episode_returns(oracle, ctrl, cfg, inst, starts)
        assert (best - exact).min() >= -1e-9, m
        regret[m] = float((best - exact).mean())
    assert abs(regret["interruption"]) < 5e-4
    assert abs(regret["options"] - 7.2) < 5e-3


def test_eval_reports_regret_per_method_and_episode(windy_tiny_bundle, tmp_path):
    m = eval_bundle(
        windy_tiny_bundle, "all", "south", episodes=60, out_dir=tmp_path, progress=False
    )
    per = m["points"][0]["methods"]
    with open(tmp_path / "episodes.csv") as f:
        rows = list(csv.DictReader(f))
    optimum = {r["episode"]: float(r["optimum_return"]) for r in rows if r["optimum_return"]}
    assert len(optimum) == 60  # once per episode
    assert "informed" in per  # informed.pt beside the bundle: it plays beside the paper's methods
    for name, r in per.items():
        assert {"regret_mean", "regret_ci95"} <= set(r)
        column = "return" if r.get("regret_sampled") else "exact_return"  # baselines: sampled
        regret = [optimum[x["episode"]] - float(x[column]) for x in rows if x["method"] == name]
        if column == "exact_return":  # the optimum is at least every controller, exactly
            assert min(regret) >= -1e-9, name
        assert abs(np.mean(regret) - r["regret_mean"]) < 1e-9
    assert "regret" in format_table(m).splitlines()[1]
    one = eval_bundle(windy_tiny_bundle, "options", "south", episodes=20, progress=False)
    assert one["regret_mean"] >= -1e-9 and "regret_ci95" in one


def test_regret_by_the_hidden_parameter_is_recomputed_from_the_episodes(
    windy_tiny_bundle, tmp_path
):
    m = eval_bundle(
        windy_tiny_bundle, "all", "train", episodes=80, out_dir=tmp_path, progress=False
    )
    data = m["regret_by_instance"]
    assert data["field"] == "p" and len(data["groups"]) == 8
    assert (tmp_path / "regret.png").exists() and "regret.png" in m["figures"]
    with open(tmp_path / "episodes.csv") as f:
        rows = list(csv.DictReader(f))
    optimum = {r["episode"]: float(r["optimum_return"]) for r in rows if r["optimum_return"]}
    first = [r for r in rows if r["method"] == m["methods"][0]]
    p = np.array([float(r["instance_p"]) for r in first])
    edges = np.quantile(p, np.linspace(0, 1, 9))
    for name, d in data["methods"].items():
        mine = {r["episode"]: r for r in rows if r["method"] == name}
        column = "return" if d["sampled"] else "exact_return"  # baselines: sampled returns
        for g, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
            inside = [
                r["episode"]
                for r in first
                if lo <= float(r["instance_p"]) and (float(r["instance_p"]) < hi or g == 7)
            ]
            want = np.mean([optimum[e] - float(mine[e][column]) for e in inside])
            assert abs(d["mean"][g] - want) < 1e-9, (name, g)
        assert d["sampled"] is (name == "informed")
    # the groups' episode-weighted mean is the method's overall regret
    sizes = np.histogram(p, edges)[0]
    for name, d in data["methods"].items():
        overall = np.dot(sizes, d["mean"]) / sizes.sum()
        assert abs(overall - m["points"][0]["methods"][name]["regret_mean"]) < 1e-9


def test_no_regret_without_an_oracle():
    """Wargus brings no oracle, nor do windy layouts too large for it: no optimum to compare."""
    for config in ("configs/wargus.yaml", "configs/windy_large.yaml"):
        cfg = load_config(config)
        (point,) = shift_points(cfg, None, [])
        assert point_oracle(cfg, point) is None, config
    row = {"mean_return": 1.0, "mean_return_ci95": 0.1, "mean_length": 5.0}
    table = format_table(
        {
            "family": "wargus",
            "checkpoint": "x",
            "test": "nominal",
            "test_description": "",
            "episodes": 1,
            "seed": 0,
            "shifts": [],
            "points": [{"shift": None, "methods": {"averaging": row}}],
        }
    )
    assert "regret" in table.splitlines()[1] and "nan" not in table
