"""The Taxi family end to end, through the public door only (docs/taxi.md): its entry point, its
own ``env.taxi`` keys, shifts of its instance fields, training and ``taskvar eval`` with the exact
oracle's figures, and options that never start outside their initiation sets."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs import TransformedEnv

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.experiments.bundle_eval import eval_bundle, format_table
from taskvar_torch.experiments.shift import parse_shift, shift_points
from taskvar_torch.factory import load_heads, make_method_controller
from taskvar_torch.families import FAMILIES, family
from taskvar_torch.families.taxi.env import TaxiEnv
from taskvar_torch.families.taxi.oracle import TaxiOracle
from taskvar_torch.families.taxi.subtasks import TaxiSubtasks
from taskvar_torch.training import train
from taskvar_torch.training.baselines import train_baseline

torch.set_num_threads(1)
CONFIG = "configs/taxi.yaml"
TINY = [
    "env.num_envs=16",
    "train.total_frames=3000",
    "train.frames_per_batch=256",
    "train.init_random_frames=1000",
    "train.eps_decay_frames=2000",
    "train.updates_per_batch=2",
    "train.checkpoint_every=0",
    "train.log_every=3000",
    "baseline.informed_frames=null",  # the baselines at the test's budget, not the config's 900k
]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    out = tmp_path_factory.mktemp("taxi")
    cfg = load_config(CONFIG, TINY)
    result = train(cfg, out, progress=False)
    train_baseline(cfg, "informed", out)  # the informed baseline beside it, the same budget
    return result["final"]


def test_taxi_comes_through_the_entry_point_with_its_own_keys():
    fam = family("taxi")
    assert "taxi" in FAMILIES and fam.config_class is not None
    assert FAMILIES._families["taxi"] is fam  # loaded from the package's own entry point
    cfg = load_config(CONFIG, ["env.taxi.obs_encoding=factored", "env.taxi.horizon=50"])
    env = fam.make_env(cfg, 2)
    assert isinstance(env, TaxiEnv) and env.horizon == 50
    assert env.reset()[keys.OBSERVATION].shape == (2, 19)
    with pytest.raises(ValueError, match=r"env\.taxi\.obs_encoding must be one of"):
        load_config(CONFIG, ["env.taxi.obs_encoding=pixels"])


def test_shifts_pin_the_rain_and_the_passenger():
    cfg = load_config(CONFIG)
    points = shift_points(cfg, "dry", [parse_shift("env.instances.rainy_probability=0.6,1.0")])
    assert [(p.instances.rain_share, p.instances.q_low) for p in points] == [(1.0, 0.6), (0.0, 1.0)]
    (point,) = shift_points(cfg, "train", [parse_shift("env.instances.fickle_probability=1")])
    assert (point.instances.fickle_share, point.instances.f_low) == (1.0, 1.0)


@pytest.mark.slow
def test_eval_all_methods_prints_the_exact_oracle_beside_the_sampled_returns(bundle):
    metrics = eval_bundle(bundle, method="all", episodes=200, test="fickle", progress=False)
    per = metrics["points"][0]["methods"]
    assert set(per) == {"averaging", "options", "interruption", "informed"}
    assert per["informed"]["regret_sampled"] and "exact_mean_return" not in per["informed"]
    for m, r in per.items():
        if m == "informed":  # not memoryless: no exact value
            continue
        # the sampled mean return within 4 standard errors of the exact expectation of the same
        # 200 episodes (each episode's instance and start, exact over the rain and the redraw)
        assert (
            abs(r["mean_return"] - r["exact_mean_return"])
            <= 4 * r["mean_return_ci95"] / 1.96 + 1e-6
        ), m


@pytest.mark.slow
@pytest.mark.parametrize("method", ["options", "interruption"])
def test_no_option_starts_outside_its_initiation_set(bundle, method):
    heads, cfg = load_heads(bundle)
    subtasks = TaxiSubtasks()
    for name, heads_of in (("learnt", heads), ("oracle", None)):
        if heads_of is None:
            heads_of = TaxiOracle(horizon=200).heads(keys.CELL, dtype=torch.float32)
        ctrl = make_method_controller(cfg, method, heads_of, subtasks)
        env = TransformedEnv(family(cfg).make_env(cfg, 64, instances="storm"), ctrl.primer())
        td = env.rollout(120, ctrl, break_when_any_done=False)
        started = td[keys.OPTION] != td[keys.RUNNING_OPTION]  # (N, T) a new option took over
        init = subtasks.initiation(td)  # (N, T, O)
        opt = td[keys.OPTION]
        ok = init.gather(-1, opt.clamp(min=0).unsqueeze(-1)).squeeze(-1) | (opt < 0)
        assert bool(started.any()), name
        assert bool(ok[started].all()), f"{name}: an option started outside its initiation set"


@pytest.mark.slow
def test_the_oracle_heads_make_interruption_pay_on_fickle_passengers():
    """Exact, not sampled: on very fickle passengers the options controller keeps driving to the
    old destination, interruption drops it (one firing per redraw) and matches the averaging
    policy (docs/taxi.md)."""
    oracle = TaxiOracle(horizon=200)
    ret = {m: float(oracle.controller_expected_return(m, "fickle")) for m in ("averaging",
           "options", "interruption")}  # fmt: skip
    assert ret["interruption"] > ret["options"] + 5.0
    assert abs(ret["interruption"] - ret["averaging"]) < 0.05
    fires = float(oracle.controller_expected_return("interruption", "fickle", count_fires=True))
    assert 0.8 <= fires <= 1.0  # E f over U[0.8, 1.0] = 0.9 redraws per episode
    assert np.isfinite(list(ret.values())).all()


@pytest.mark.slow
def test_learnt_option_controllers_reach_the_exact_optimum_on_dry_instances(tmp_path):
    """A learning test against the exact oracle, with its bound stated: 120k frames on classic
    (dry) Taxi with a learning rate of 0.002, the shipped config otherwise (the expectile max-value
    head, cheaper; nothing fires without a fickle passenger). The options (MAXQ's navigation,
    pickup and dropoff) learn first: the options and interruption controllers are within 5% of the
    exact optimum (7.930 per episode) in expectation over Taxi-v4's starts. Chosen on dry training
    instances, training seeds 0 and 1: at 120k both reach 7.683 and 7.777; at 80k (this test's
    budget until the learner's informed head was removed, which changed the random stream) one
    seed reaches 7.877 and the other -44.1, so 80k was a lucky stream, not a budget. The flat
    averaging head is not reliably there yet (4.487 and 7.930 at 120k; docs/taxi.md: ~300k)."""
    cfg = load_config(
        CONFIG,
        [
            "env.instances=dry",
            "train.total_frames=120000",
            "train.eps_decay_frames=60000",
            "train.max_value_estimator=expectile",
            "train.lr=0.002",
            "train.checkpoint_every=0",
        ],
    )
    heads, cfg = load_heads(train(cfg, tmp_path, progress=False)["final"])
    oracle = TaxiOracle(train_instances="dry", obs_encoding=cfg.env.taxi.obs_encoding)
    best = float(oracle.expected_optimal_return("dry"))
    assert abs(best - 7.93) < 1e-3
    for method in ("options", "interruption"):
        ctrl = make_method_controller(cfg, method, heads, TaxiSubtasks())
        got = float(oracle.controller_expected_return(ctrl, "dry"))
        assert got >= best - 0.05 * abs(best), (method, got, best)


@pytest.mark.slow
def test_eval_skips_costly_exact_returns_unless_asked(bundle):
    """Continuous rain makes every episode its own chain solve: by default ``taskvar eval``
    skips the exact column there (and says so), ``exact=False`` never computes it, and dry
    instances (one rain value) always get it."""
    metrics = eval_bundle(bundle, method="averaging", episodes=200, test="train", progress=False)
    assert "exact_mean_return" not in metrics and "too many distinct" in metrics["exact_skipped"]
    assert "too many distinct" in format_table(metrics)
    dry = eval_bundle(bundle, method="averaging", episodes=40, test="dry", progress=False)
    assert "exact_mean_return" in dry and "exact_skipped" not in dry
    off = eval_bundle(bundle, "averaging", episodes=40, test="dry", progress=False, exact=False)
    assert "exact_mean_return" not in off and "exact_skipped" not in off
