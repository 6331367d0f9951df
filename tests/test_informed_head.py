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
from taskvar_torch.train import train

SHORT = [
    "train.total_frames=4096",
    "train.init_random_frames=1024",
    "train.eps_decay_frames=2048",
    "train.checkpoint_every=0",
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
