"""The baselines as agents of their own (docs/memory.md): ``informed`` is a plain network over
[observation; instance features] on its own epsilon-greedy stream, ``blind`` the same network told
nothing, both with the heads' n-step targets; the recurrent baseline's budget key; and what the
learner's removed informed head leaves behind (its config keys and its bundles) still loads."""

from __future__ import annotations

import warnings

import pytest
import torch
from tensordict import TensorDict

from taskvar_torch.checkpoint import load_checkpoint, save_checkpoint
from taskvar_torch.cli import main
from taskvar_torch.config import load_config
from taskvar_torch.factory import load_heads
from taskvar_torch.heads.informed import informed_features
from taskvar_torch.heads.recurrent import (
    BaselineSpec,
    load_baseline,
    make_informed_qnet,
    save_baseline,
)
from taskvar_torch.training import train
from taskvar_torch.training.baselines import BaselineLearner, baseline_train_config, train_baseline

SHORT = [
    "train.total_frames=2048",
    "train.init_random_frames=512",
    "train.eps_decay_frames=1024",
    "train.checkpoint_every=0",
    "train.updates_per_batch=2",
    "train.batch_size=64",
    "env.num_envs=4",
]


def test_the_old_heads_informed_keys_load_with_one_deprecation_line(tmp_path):
    path = tmp_path / "old.yaml"
    path.write_text("family: windy\nheads:\n  informed: true\n  informed_anchor: 1.0\n")
    with pytest.warns(FutureWarning) as rec:
        cfg = load_config(str(path))
    text = " ".join(str(w.message) for w in rec)
    assert "heads.informed is dropped" in text and "train-baselines --method informed" in text
    assert not hasattr(cfg.heads, "informed")
    with pytest.warns(FutureWarning, match="heads.informed is deprecated"):
        load_config("configs/windy.yaml", ["heads.informed=true"])


def test_a_checkpoint_with_the_learners_old_informed_head_still_evaluates(tmp_path):
    """A ``final.pt`` written while the learner trained the informed head holds its tensors
    (``heads.informed.*``) beside the paper's heads: they are dropped on loading."""
    torch.set_num_threads(1)
    cfg = load_config("configs/windy.yaml", SHORT)
    run = train(cfg, tmp_path, progress=False)
    heads, _ = load_heads(run["final"])
    bundle = load_checkpoint(run["final"])
    key = "eval_heads" if "eval_heads" in bundle["models"] else "heads"
    bundle["models"][key]["heads.informed.module.mlp.0.weight"] = torch.zeros(3, 3)
    bundle["heads_spec"]["informed_dim"] = 5
    bundle["heads_spec"]["informed_residual"] = True
    old = tmp_path / "old.pt"
    save_checkpoint(old, {k: v for k, v in bundle.items() if k not in ("format", "format_version")})
    again, _ = load_heads(old)
    a, b = heads.state_dict(), again.state_dict()
    assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)


def _nets(cfg):
    dim, feats = informed_features(cfg)
    ikeys = ("p", "direction")
    args = (25, 4, dim, feats, ikeys, (16,), "relu")
    torch.manual_seed(0)
    informed = make_informed_qnet(*args)
    blind = make_informed_qnet(*args, blind=True)
    blind.load_state_dict(informed.state_dict())
    return informed, blind, dim


def _batch(n: int) -> TensorDict:
    gen = torch.Generator().manual_seed(1)
    return TensorDict(
        {
            "observation": torch.rand(n, 25, generator=gen),
            "instance": {
                "p": torch.rand(n, generator=gen),
                "direction": torch.randint(0, 4, (n,), generator=gen),
            },
        },
        [n],
    )


def test_blind_is_the_informed_network_with_the_features_zeroed():
    cfg = load_config("configs/windy.yaml")
    informed, blind, dim = _nets(cfg)
    td = _batch(16)
    q_blind = blind(td.clone())["action_value"]
    other = td.clone()
    other["instance", "p"] = 1 - other["instance", "p"]
    assert torch.equal(blind(other)["action_value"], q_blind)  # it reads nothing of the instance
    zeroed = td.clone()
    q_informed = informed(zeroed)["action_value"]
    assert not torch.equal(q_informed, q_blind)  # informed reads it
    net = informed[2].module  # the MLP over [observation; features]
    want = net(torch.cat([td["observation"], torch.zeros(16, dim)], -1))
    assert torch.allclose(q_blind, want)


def test_an_old_residual_informed_bundle_still_evaluates(tmp_path):
    """``informed.pt`` bundles the learner wrote as ``Q_avg + Delta`` (``residual``) load and play."""
    cfg = load_config("configs/windy.yaml")
    dim, feats = informed_features(cfg)
    net = make_informed_qnet(25, 4, dim, feats, ("p", "direction"), (16,), "relu", residual=True)
    spec = BaselineSpec("informed", 25, 4, (16,), instance_dim=dim)
    spec.instance_keys, spec.residual = ("p", "direction"), True
    path = save_baseline(tmp_path / "informed.pt", net, spec, cfg)
    ctrl, _ = load_baseline(path)
    td = _batch(8)
    assert ctrl.spec.residual
    assert torch.equal(ctrl(td.clone())["action_value"], net(td.clone())["action_value"])


def _stream(n_env: int, steps: int, done_at: dict[int, list[int]]) -> TensorDict:
    """A collector-like ``(N, T)`` batch: observation = a running step id, reward = 1 + step id,
    the episodes of env ``i`` ending (terminated) after the steps ``done_at[i]``."""
    obs = torch.arange(n_env * steps, dtype=torch.float32).reshape(n_env, steps, 1)
    done = torch.zeros(n_env, steps, 1, dtype=torch.bool)
    for i, ts in done_at.items():
        done[i, ts] = True
    return TensorDict(
        {
            "observation": obs,
            "action": torch.zeros(n_env, steps, dtype=torch.long),
            "next": {
                "observation": obs + 0.5,
                "reward": (obs + 1.0),
                "done": done,
                "terminated": done.clone(),
                "truncated": torch.zeros_like(done),
            },
        },
        [n_env, steps],
    )


def test_n_step_targets_follow_each_sub_env_and_stop_at_the_episode_end():
    """``train.n_step=3``: each stored row's reward is the discounted sum of up to 3 rewards of
    its own sub-env (cut at the episode's end), its next observation and done flags those of the
    step the target bootstraps from, ``steps_to_next_obs`` how many steps that is; the last 3 steps
    of a batch wait for the next one (checked against a loop over each sub-env)."""
    from torchrl.data.tensor_specs import Categorical

    cfg = load_config("configs/windy.yaml", ["train.n_step=3", "train.gamma=0.5"])
    net = make_informed_qnet(1, 2, 0, lambda td: torch.zeros(td.shape[0], 0), (), (4,), "relu")
    learner = BaselineLearner(net, Categorical(2), cfg, recurrent=False)
    first, second = _stream(2, 6, {0: [1]}), _stream(2, 6, {1: [0]})
    second["observation"] += 100
    second["next", "observation"] += 100
    second["next", "reward"] += 100
    learner.store(first)
    learner.store(second)
    rows = learner.buffer[:]
    whole = torch.cat([first, second], 1)  # (2, 12) each sub-env's stream
    got = {float(o): r for o, r in zip(rows["observation"].reshape(-1), rows.unbind(0))}
    assert len(got) == 2 * (12 - 3)
    for i in range(2):
        for t in range(12 - 3):
            k, ret = 0, 0.0
            while True:
                ret += 0.5**k * float(whole["next", "reward"][i, t + k])
                k += 1
                if k == 3 or bool(whole["next", "done"][i, t + k - 1]):
                    break
            r = got[float(whole["observation"][i, t])]
            assert float(r["next", "reward"]) == pytest.approx(ret), (i, t)
            assert int(r["steps_to_next_obs"]) == k
            assert float(r["next", "observation"]) == float(
                whole["next", "observation"][i, t + k - 1]
            )
            assert bool(r["next", "terminated"]) == bool(whole["next", "terminated"][i, t + k - 1])


def test_the_budget_keys_scale_their_schedule_and_nothing_else():
    cfg = load_config("configs/taxi.yaml")
    assert cfg.baseline.recurrent_frames == 1_200_000
    t = baseline_train_config(cfg, "recurrent")
    assert (t.total_frames, t.eps_decay_frames) == (1_200_000, 600_000)
    assert t.eval_ema_tau == cfg.train.eval_ema_tau  # informed_ema_tau is not the recurrent one's
    assert (cfg.baseline.informed_frames, cfg.baseline.informed_ema_tau) == (900_000, 0.01)
    for m in ("informed", "blind"):  # the same budget and evaluation average for both (issue 56)
        t = baseline_train_config(cfg, m)
        assert (t.total_frames, t.eps_decay_frames, t.eval_ema_tau) == (900_000, 450_000, 0.01)
        keep = ("lr", "batch_size", "updates_per_batch", "target_tau", "n_step", "double_q")
        assert all(getattr(t, k) == getattr(cfg.train, k) for k in keep)
    windy = load_config("configs/windy.yaml")
    for m in ("recurrent", "informed", "blind"):
        assert baseline_train_config(windy, m) is windy.train
    for key in ("recurrent_frames", "informed_frames"):
        with pytest.raises(ValueError, match=f"baseline.{key}"):
            load_config("configs/windy.yaml", [f"baseline.{key}=0"])
    with pytest.raises(ValueError, match="baseline.informed_ema_tau"):
        load_config("configs/windy.yaml", ["baseline.informed_ema_tau=1.5"])


@pytest.mark.slow  # a real process or several agents trained: make test only
def test_train_baselines_all_writes_the_three_agents_and_eval_plays_them(tmp_path):
    torch.set_num_threads(1)
    out = tmp_path / "run"
    tiny = ["train.total_frames=1024", "train.init_random_frames=256", "env.num_envs=4"]
    argv = ["configs/windy.yaml", *tiny, "--out", str(out), "--no-progress"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        assert main(["train", *argv, "train.checkpoint_every=0"]) == 0
        assert main(["train-baselines", *argv, "--method", "all", "--threads", "1"]) == 0
    for m in ("recurrent", "informed", "blind"):
        ctrl, _ = load_baseline(out / f"{m}.pt")
        assert ctrl.spec.method == m and ctrl.total_frames == 1024
    assert not (out / "informed.pt").samefile(out / "blind.pt")
    r = train_baseline(load_config("configs/windy.yaml", tiny), "blind", tmp_path / "b")
    assert r["budget"] == 1024
