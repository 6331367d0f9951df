"""The informed baseline as one more head of the learner (``heads.informed``; docs/memory.md):
the paper's heads are the same bits with it on or off, it is written as ``informed.pt`` beside
``final.pt`` (and in every seed's folder), a family without instance features refuses it in one
line, and on Taxi it reaches the exact optimum of the dry instances within a stated bound."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from taskvar_torch import families
from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, load_heads, make_env, make_subtasks
from taskvar_torch.heads.recurrent import load_baseline
from taskvar_torch.training import train

SHORT = [  # what these tests check holds for any number of updates: few and small ones
    "train.total_frames=4096",
    "train.init_random_frames=1024",
    "train.eps_decay_frames=2048",
    "train.checkpoint_every=0",
    "train.updates_per_batch=4",
    "train.batch_size=64",
]


def _train(tmp_path, config, *overrides):
    torch.set_num_threads(1)
    cfg = load_config(config, [*SHORT, *overrides])
    return train(cfg, tmp_path, progress=False)


@pytest.mark.parametrize("config", ["configs/windy.yaml", "configs/wargus.yaml"])
def test_paper_heads_are_the_same_bits_with_the_informed_head(tmp_path, config):
    extra = ["train.compile=false"]
    off = _train(tmp_path / "off", config, "heads.informed=false", *extra)
    on = _train(tmp_path / "on", config, "heads.informed=true", *extra)
    a = load_checkpoint(off["final"])["models"]["heads"]
    b = load_checkpoint(on["final"])["models"]["heads"]
    informed = [k for k in b if k.startswith("heads.informed.")]
    assert informed and not any(k.startswith("heads.informed.") for k in a)
    assert set(b) - set(informed) == set(a)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert "loss_informed" in on["last_log"] and "loss_informed" not in off["last_log"]
    assert not (tmp_path / "off" / "informed.pt").exists()
    ctrl, cfg = load_baseline(tmp_path / "on" / "informed.pt")
    assert ctrl.spec.mlp == tuple(cfg.heads.hidden)  # the averaging head's widths


def test_informed_bundle_holds_the_heads_evaluation_weights(tmp_path):
    """``informed.pt`` plays the learner's informed head ``Q_avg + Delta``: its ``Delta`` is the
    head's Polyak-averaged weights (``train.eval_ema_tau``), its ``Q_avg`` a copy of the
    averaging head's, and it gives the heads' Q-values on the same input (self-contained)."""
    _train(tmp_path, "configs/windy_corridor.yaml", "heads.informed=true", "train.eval_ema_tau=0.1")
    bundle = load_checkpoint(tmp_path / "final.pt")
    ema = {
        k.removeprefix("heads.informed.module.mlp."): v
        for k, v in bundle["models"]["eval_heads"].items()
        if k.startswith("heads.informed.")
    }
    ctrl, _ = load_baseline(tmp_path / "informed.pt")
    assert ctrl.spec.residual
    q = ctrl.net[1].module
    delta = q.delta.state_dict()
    assert set(delta) == set(ema)
    for k in delta:
        assert torch.equal(delta[k], ema[k])
    online = bundle["models"]["heads"]["heads.informed.module.mlp.0.weight"]
    assert not torch.equal(online, ema["0.weight"])  # the average, not the online weights
    heads, _ = load_heads(tmp_path / "heads.pt")  # the evaluation heads
    gen = torch.Generator().manual_seed(0)
    obs = torch.rand(32, heads.spec.obs_dim, generator=gen)
    z = torch.rand(32, heads.spec.informed_dim, generator=gen)
    with torch.no_grad():
        want = heads.heads["averaging"].module(obs) + heads.heads["informed"].module(obs, z)
        assert torch.allclose(q(obs, z), want, atol=1e-5)


def test_informed_head_starts_as_the_averaging_head():
    """``Delta``'s last layer is zero at initialisation: ``Q_inf = Q_avg`` before any update."""
    cfg = load_config("configs/taxi.yaml", ["env.num_envs=2"])
    env = make_env(cfg, 2)
    heads = build_heads(cfg, env, make_subtasks(cfg, env))
    net = heads.heads["informed"].module
    assert net.residual
    obs = torch.rand(8, heads.spec.obs_dim)
    z = torch.rand(8, heads.spec.informed_dim)
    assert torch.equal(net(obs, z), torch.zeros(8, heads.spec.num_actions))


def test_every_seed_folder_gets_its_informed_bundle(tmp_path):
    _train(tmp_path, "configs/windy.yaml", "heads.informed=true", "train.seeds=2")
    for k in (0, 1):
        ctrl, cfg = load_baseline(tmp_path / f"seed{k}" / "informed.pt")
        assert cfg.seed == k and ctrl.spec.method == "informed"


def test_a_family_without_instance_features_refuses_it_in_one_line(monkeypatch):
    from taskvar_torch.config import validate

    fam = families.family
    bare = lambda c: dataclasses.replace(fam(c), informed_features=None, instance_features=None)  # noqa: E731
    monkeypatch.setattr(validate, "family", bare)
    with pytest.raises(ValueError) as e:
        load_config("configs/windy.yaml", ["heads.informed=true"])
    msg = str(e.value)
    assert "\n" not in msg and "heads.informed=true needs a family" in msg
    assert "set heads.informed=false" in msg


DRY_BUDGET = [
    "env.instances=dry",
    "train.total_frames=150000",
    "train.eps_decay_frames=75000",
    "train.lr=0.002",
    "train.max_value_estimator=expectile",
    "train.checkpoint_every=0",
]
DRY_BOUND = 0.08
"""Stated bound on the informed head's exact expected return below the exact optimum on Taxi's dry
instances (7.930 per episode over Taxi-v4's starts): 1%, as the options' dry test."""


def informed_dry_policy(folder, cfg) -> torch.Tensor:
    """The greedy action ``(500,)`` of ``folder/informed.pt`` (the file ``taskvar eval`` plays) in
    every Taxi state of a dry instance (its features as a dry env's reset gives them)."""
    from tensordict import TensorDict

    from taskvar_torch.families.taxi.env import observation_table

    ctrl, _ = load_baseline(folder / "informed.pt")
    dry = make_env(cfg, 1).reset()["instance"]
    obs = torch.as_tensor(observation_table(cfg.env.taxi.obs_encoding))
    td = TensorDict({"observation": obs, "instance": dry.expand(obs.shape[0]).clone()}, [500])
    return ctrl(td)["action"].long()


@pytest.mark.slow
def test_informed_reaches_the_exact_optimum_on_dry_taxi(tmp_path):
    """A learning test against the exact oracle, with its bound stated: trained on dry instances
    (150k frames, lr 0.002, the expectile max-value head, the shipped config otherwise), the
    informed head's greedy policy from ``informed.pt`` is within :data:`DRY_BOUND` of the exact
    optimum (7.930) in expectation over Taxi-v4's starts.

    Measured (exact, seeds 0, 1, 2): 7.930 on all three at this budget; the test takes 44 s on
    one core of the 2-core CPU (60-100 s of training with a third process on it); at 120k frames 1.79, 7.93, 2.45 and at 100k -68.2, -21.7 (seeds 0, 1):
    the flat heads (averaging, and so informed = averaging + Delta) need about this budget on
    dry Taxi, so no cheaper run held it."""
    from taskvar_torch.families.taxi.oracle import TaxiOracle

    torch.set_num_threads(1)
    cfg = load_config("configs/taxi.yaml", DRY_BUDGET)
    train(cfg, tmp_path, progress=False)
    oracle = TaxiOracle(train_instances="dry", obs_encoding=cfg.env.taxi.obs_encoding)
    best = float(oracle.expected_optimal_return("dry"))
    assert abs(best - 7.93) < 1e-3
    got = float(oracle.expected_return(informed_dry_policy(tmp_path, cfg), "dry"))
    assert got >= best - DRY_BOUND, (got, best)
