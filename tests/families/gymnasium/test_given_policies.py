"""Options that are the user's own controllers (``Option(name, policy=fn)``; docs/gymnasium.md):
a family whose only option is a given balancing controller plays it exactly (its ``options``
return equals the controller's own in the raw Gymnasium env), the learner learns that option's
values under the given policy, a policy that returns no action of the space is refused in one
line naming the option, and a misspelt attribute instance key is refused in one line."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import TransformedEnv

from taskvar_torch import check_family, keys, rng
from taskvar_torch.config import load_config
from taskvar_torch.experiments.evaluation import run_episodes
from taskvar_torch.factory import load_heads, make_method_controller, make_subtasks
from taskvar_torch.families import FAMILIES, register_family
from taskvar_torch.families.gymnasium import Option, gym_family
from taskvar_torch.families.gymnasium.instances import reset_seed
from taskvar_torch.heads.bundle import with_given_policies
from taskvar_torch.training import train

torch.set_num_threads(1)
HORIZON = 60


@dataclass(frozen=True)
class PoleLength:
    low: float = 0.3
    high: float = 0.7

    def sample(self, rng):
        return {"length": float(rng.uniform(self.low, self.high))}


def balance(obs, info) -> int:
    """A hand-written PD balancer of CartPole's pole: push towards where the pole falls."""
    return int(obs[2] + 0.5 * obs[3] > 0)


def apply_length(env, instance):
    """CartPole caches ``polemass_length = masspole * length`` in its constructor."""
    env.length = instance["length"]
    env.polemass_length = env.masspole * env.length


def given_cartpole(name="given_cartpole", policy=balance, **kw):
    return gym_family(
        name, "CartPole-v1", {"train": PoleLength()}, [Option("balance", policy=policy)],
        instance_via="attributes", apply=apply_length, horizon=HORIZON, **kw,
    )  # fmt: skip


@pytest.fixture
def registered():
    names = []

    def add(fam):
        register_family(fam, replace=True)
        names.append(fam.name)
        return fam

    yield add
    for name in names:
        FAMILIES._families.pop(name, None)


def _cfg(fam, tmp_path, *overrides):
    path = tmp_path / "cfg.yaml"
    path.write_text(f"family: {fam.name}\nenv:\n  num_envs: 4\n")
    return load_config(path, list(overrides))


def test_the_given_controllers_action_wins_every_argmax_and_max():
    q = torch.tensor([[[1.0, 5.0, 2.0], [1.0, 5.0, 2.0]]])  # (B=1, O=2, A=3)
    given = torch.tensor([[2, -1]])  # option 0 given (action 2), option 1 learnt
    m = with_given_policies(q, given)
    assert m.argmax(-1).tolist() == [[2, 1]]
    assert m.max(-1).values.tolist() == [[2.0, 5.0]]  # Q_o(s, pi_o(s)) for the given one
    assert with_given_policies(q, None) is q


def test_a_family_whose_only_option_is_a_given_controller_plays_it_exactly(registered, tmp_path):
    """Trained briefly (its values are learnt, its actions are the controller's), the options
    controller's return on each sub-environment's first episode equals running ``balance`` in the
    raw CartPole-v1 with that episode's pole length and reset seed."""
    fam = registered(given_cartpole())
    check_family(fam)
    tiny = ["train.total_frames=1024", "train.init_random_frames=256", "train.checkpoint_every=0"]
    cfg = _cfg(fam, tmp_path, *tiny)
    train(cfg, tmp_path / "run", progress=False)
    heads, cfg = load_heads(tmp_path / "run" / "final.pt")
    n, seed = 6, 5
    env = fam.make_env(cfg, n, seed=seed)
    ctrl = make_method_controller(cfg, "options", heads, make_subtasks(cfg, env))
    out = run_episodes(TransformedEnv(env, ctrl.primer()), ctrl, max_steps=HORIZON)
    env.close()
    for i in range(n):
        key = int(rng.episode_key(rng.sub_env_key(seed, torch.tensor(i)), 0))
        raw = gym.make("CartPole-v1")
        apply_length(raw.unwrapped, {"length": float(out["instance", "length"][i])})
        obs, info = raw.reset(seed=reset_seed(key))
        total, t, done = 0.0, 0, False
        while not done and t < HORIZON:
            obs, r, term, trunc, info = raw.step(balance(obs, info))
            total, t, done = total + r, t + 1, term or trunc
        assert float(out["return"][i]) == total, (i, float(out["return"][i]), total)
    assert float(out["return"].min()) > 20  # the balancer holds the pole for a while


def test_a_policy_that_returns_no_action_is_refused_naming_the_option(registered, tmp_path):
    for bad in (lambda o, i: "left", lambda o, i: None, lambda o, i: 7, lambda o, i: np.zeros(2)):
        fam = registered(given_cartpole("bad_policy", policy=bad))
        env = None
        with pytest.raises(ValueError) as e:
            env = fam.make_env(_cfg(fam, tmp_path), 2, seed=0)
            env.reset()
        msg = str(e.value)
        assert "\n" not in msg and "option 'balance' policy(obs, info) returned" in msg
        assert "not an action of Discrete(2)" in msg
        if env is not None:
            env.close()
    with pytest.raises(ValueError, match="policy must be callable"):
        Option("x", policy=3)


def test_a_misspelt_attribute_instance_key_is_refused_in_one_line(registered, tmp_path):
    @dataclass(frozen=True)
    class Typo:
        def sample(self, rng):
            return {"lenght": 0.5}

    fam = registered(
        gym_family(
            "typo",
            "CartPole-v1",
            {"train": Typo()},
            [Option("balance", policy=balance)],
            instance_via="attributes",
            horizon=HORIZON,
        )  # fmt: skip
    )
    with pytest.raises(ValueError) as e:
        fam.make_env(_cfg(fam, tmp_path), 2, seed=0).reset()
    msg = str(e.value)
    assert "\n" not in msg and "instance key 'lenght' is not an attribute of CartPoleEnv" in msg


def test_given_actions_reach_the_tensordict_as_indices_from_zero(registered, tmp_path):
    """A learnt option beside a given one: -1 for the learnt, the controller's action for the
    given one, an index from 0 even where the action space starts elsewhere."""
    fam = registered(
        gym_family(
            "mixed",
            "CartPole-v1",
            {"train": PoleLength()},
            [Option("free"), Option("balance", policy=balance)],
            instance_via="attributes",
            horizon=HORIZON,
        )  # fmt: skip
    )
    env = fam.make_env(_cfg(fam, tmp_path), 3, seed=1)
    td = env.reset()
    given = td["subtask", "given_action"]
    obs = td[keys.OBSERVATION]
    assert given[:, 0].tolist() == [-1, -1, -1]
    assert given[:, 1].tolist() == [balance(o.numpy(), {}) for o in obs]
    sub = make_subtasks(load_config(tmp_path / "cfg.yaml"), env)
    assert sub.given == (False, True) and torch.equal(sub.given_actions(td), given)
    env.close()


def cartpole_hierarchy():
    """A composition hierarchy through the adapter (paper §3.4.2): the given balancer and a learnt
    centring option under the full task, each with its robustness reward as a function."""

    def upright(obs, info, reward):  # +1 while the pole stays within 6 degrees
        return 1.0 if abs(obs[2]) < 0.1 else -1.0

    def centred(obs, info, reward):
        return 1.0 if abs(obs[0]) < 0.5 else -1.0

    opts = [
        Option("balance", policy=balance, robustness=upright),
        Option("center", reward=lambda o, i, r: 1.0 - abs(float(o[0])), robustness=centred),
        Option("task", robustness=lambda o, i, r: upright(o, i, r) + centred(o, i, r)),
    ]
    return gym_family(
        "cartpole_tree", "CartPole-v1", {"train": PoleLength()}, opts,
        instance_via="attributes", apply=apply_length, horizon=HORIZON,
        hierarchy={"root": "task", "children": {"task": ["balance", "center"]}},
    )  # fmt: skip


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_a_declared_hierarchy_makes_eval_all_play_the_hierarchy(registered, tmp_path):
    from taskvar_torch.cli import main

    fam = registered(cartpole_hierarchy())
    check_family(fam)
    path = tmp_path / "cfg.yaml"
    path.write_text(f"family: {fam.name}\nenv:\n  num_envs: 4\n")
    tiny = ["train.total_frames=1024", "train.init_random_frames=256", "train.checkpoint_every=0"]
    run = tmp_path / "run"
    assert main(["train", str(path), *tiny, "--out", str(run), "--no-progress"]) == 0
    ev = ["eval", "--checkpoint", str(run / "final.pt"), "--method", "all", "--episodes", "8"]
    assert main([*ev, "--out", str(tmp_path / "eval"), "--no-progress"]) == 0
    import json

    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert m["methods"] == ["averaging", "options", "interruption", "hierarchy"]
    control = m["points"][0]["methods"]["hierarchy"]["control"]
    assert abs(sum(control.values()) - 1.0) < 1e-9


def test_a_hierarchy_of_options_without_robustness_is_refused_in_one_line():
    with pytest.raises(ValueError) as e:
        gym_family(
            "bad_tree", "CartPole-v1", {"train": PoleLength()},
            [Option("balance", policy=balance), Option("task")], instance_via="attributes",
            horizon=HORIZON, hierarchy={"root": "task", "children": {"task": ["balance"]}},
        )  # fmt: skip
    assert "hierarchy option 'task' has no robustness function" in str(e.value)
    with pytest.raises(ValueError, match="'nope', which is not an option"):
        gym_family(
            "bad_tree", "CartPole-v1", {"train": PoleLength()}, [Option("balance")],
            instance_via="attributes", horizon=HORIZON,
            hierarchy={"root": "nope", "children": {}},
        )  # fmt: skip


def test_exact_and_by_frames_on_a_family_without_an_oracle_are_one_line_errors(
    registered, tmp_path, capsys
):
    from taskvar_torch.cli import main

    fam = registered(given_cartpole("no_oracle"))
    path = tmp_path / "cfg.yaml"
    path.write_text(f"family: {fam.name}\nenv:\n  num_envs: 4\n")
    tiny = ["train.total_frames=512", "train.init_random_frames=256", "train.checkpoint_every=0"]
    run = tmp_path / "run"
    assert main(["train", str(path), *tiny, "--out", str(run), "--no-progress"]) == 0
    capsys.readouterr()
    for flag in ("--exact", "--by-frames"):
        argv = ["eval", "--checkpoint", str(run / "final.pt"), flag, "--episodes", "4"]
        assert main([*argv, "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "needs an exact oracle" in err
        assert "family 'no_oracle' has none" in err


def test_check_family_takes_a_new_object_of_an_installed_family(registered):
    """An installed family's ``family()`` returns a new object each call: ``check_family`` checks
    it under its name and leaves the registered one in place."""
    installed = registered(given_cartpole("installed"))
    check_family(given_cartpole("installed"))
    assert FAMILIES._families["installed"] is installed
