"""The MiniGrid family end to end, through the public door only (docs/minigrid.md): its entry point
and ``env.minigrid`` keys, the sealed layout split, the options' events on rollouts, the conv
heads over the view, and ``taskvar train`` / ``taskvar eval --method all`` on both configs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from taskvar_torch import cli, keys
from taskvar_torch.config import load_config
from taskvar_torch.factory import HeadSpec, build_heads
from taskvar_torch.families import FAMILIES, family
from taskvar_torch.families.minigrid import dynamics as D
from taskvar_torch.families.minigrid.env import CARRYING, DOOR, SIDE, MiniGridEnv, encode
from taskvar_torch.families.minigrid.layouts import HELDOUT_SHARE, LayoutSampler, layouts

torch.set_num_threads(1)
DOORKEY, LAVAGAP = "configs/minigrid_doorkey.yaml", "configs/minigrid_lavagap.yaml"
TINY = [
    "env.num_envs=16",
    "env.minigrid.max_steps=40",
    "train.total_frames=1024",
    "train.frames_per_batch=256",
    "train.init_random_frames=512",
    "train.eps_decay_frames=512",
    "train.updates_per_batch=1",
    "train.batch_size=32",
    "train.log_every=1024",
    "eval.episodes=16",
    "eval.batch_size=16",
]


def test_minigrid_comes_through_the_entry_point_with_its_own_keys():
    fam = family("minigrid")
    assert FAMILIES._families["minigrid"] is fam
    cfg = load_config(DOORKEY, ["env.minigrid.size=8", "env.minigrid.obs_encoding=image"])
    env = fam.make_env(cfg, 2)
    assert isinstance(env, MiniGridEnv) and env.horizon == 640 and env.size == 8
    assert env.reset()[keys.OBSERVATION].shape == (2, 151)
    for override, field in (
        ("env.minigrid.task=fourrooms", "task"),
        ("env.minigrid.obs_encoding=pixels", "obs_encoding"),
        ("env.minigrid.size=4", "size"),
    ):
        with pytest.raises(ValueError, match=rf"env\.minigrid\.{field} must be") as e:
            load_config(DOORKEY, [override])
        assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    ("task", "size"),
    [("doorkey", 5), ("doorkey", 6), ("doorkey", 8), ("lavagap", 5), ("lavagap", 7)],
)
def test_the_held_out_layouts_are_a_fixed_fifth_never_drawn_in_training(task, size):
    table = layouts(task, size)
    M = table.num_layouts
    assert int(table.heldout.sum()) == math.ceil(M / HELDOUT_SHARE) and M - table.heldout.sum() > 0
    assert math.isclose(table.prob.sum(), 1.0)
    keys_ = torch.arange(4000) * 2654435761 % (1 << 32)
    for name, allowed in (("train", ~table.heldout), ("heldout", table.heldout)):
        drawn = LayoutSampler(task, size, name).draw(keys_)["layout"]
        assert bool(torch.as_tensor(allowed)[drawn].all()), name
        assert len(set(drawn.tolist())) == int(allowed.sum()), name  # every layout of its side


@pytest.mark.parametrize("config", [DOORKEY, LAVAGAP])
def test_the_options_fire_on_their_events(config):
    """On random rollouts: exactly one component is initiable in every state, each component's
    subtask reward is +1 exactly on its event, and it terminates exactly outside its initiation
    set or at the goal."""
    cfg = load_config(config)
    fam = family(cfg)
    env = fam.make_env(cfg, 64, seed=3)
    sub = fam.subtasks(cfg, env)
    g = torch.Generator().manual_seed(0)
    td = env.reset()
    rows = []
    for _ in range(120):  # pickup, toggle and forward more often than chance: more events
        a = torch.randint(0, D.NUM_ACTIONS, (64,), generator=g)
        a = torch.where(torch.rand(64, generator=g) < 0.5, torch.tensor([2, 3, 5])[a % 3], a)
        stepped, td = env.step_and_maybe_reset(td.set(keys.ACTION, a))
        rows.append(stepped.clone())
    batch = torch.stack(rows).reshape(-1)
    nxt = batch["next"]
    init, reward, beta = sub.initiation(batch), sub.reward(batch), sub.termination(nxt)
    assert bool((init[:, :-1].sum(-1) == 1).all()) and bool(init[:, -1].all())
    goal = nxt[keys.REWARD].squeeze(-1) > 0
    assert torch.equal(reward[:, -1], nxt[keys.REWARD].squeeze(-1))
    if cfg.env.minigrid.task == "doorkey":
        picked = (batch[CARRYING] != D.OBJECT_TO_IDX["key"]) & (
            nxt[CARRYING] == D.OBJECT_TO_IDX["key"]
        )
        opened = (batch[DOOR] != 0) & (nxt[DOOR] == 0)
        events = [picked, opened, goal]
    else:
        events = [(batch[SIDE] == 0) & (nxt[SIDE] == 1), goal]
    for o, event in enumerate(events):
        assert bool(event.any()), sub.names[o]
        assert torch.equal(reward[:, o], event.to(torch.float32)), sub.names[o]
    next_init = sub.initiation(nxt)
    assert torch.equal(beta[:, :-1], ~next_init[:, :-1] | goal.unsqueeze(-1))
    assert not bool(beta[:, -1].any())


def test_conv_heads_read_the_view():
    cfg = load_config(LAVAGAP)
    assert cfg.heads.network == "conv"
    env = family(cfg).make_env(cfg, 3)
    spec = HeadSpec.of(cfg, env, family(cfg).subtasks(cfg, env))
    heads = build_heads(cfg, spec)
    obs = env.reset()[keys.OBSERVATION]
    assert heads.heads["options"].module(obs).shape == (3, 3, D.NUM_ACTIONS)


def test_the_observation_encodes_minigrids_image():
    env = MiniGridEnv(8, task="doorkey", size=6, seed=1)
    td = env.reset()
    image, direction = env.image(), env._dir
    assert torch.equal(td[keys.OBSERVATION], encode(image, direction, "onehot"))
    raw = encode(image, direction, "image")[:, 4:].view(8, 3, 7, 7)  # (C, vy, vx)
    assert torch.equal(raw.permute(0, 3, 2, 1).to(torch.uint8), image)


@pytest.mark.slow
@pytest.mark.parametrize("config", [DOORKEY, LAVAGAP])
def test_train_and_eval_every_method_through_the_command(config, tmp_path, capsys):
    out = tmp_path / "run"
    cli.main(["train", config, "--out", str(out), *TINY])
    cli.main(
        [
            "eval",
            "--checkpoint",
            str(out / "final.pt"),
            "--method",
            "all",
            "--test",
            "heldout",
            "--episodes",
            "16",
            "--out",
            str(tmp_path / "eval"),
        ]
    )
    text = capsys.readouterr().out
    for method in ("averaging", "options", "interruption", "hierarchy"):
        assert method in text


@pytest.mark.slow
def test_heads_trained_on_the_port_play_the_same_in_minigrids_own_env(tmp_path):
    """A bundle trained on the port, its greedy averaging policy played in ``gym.make``'s
    MiniGrid env (observations encoded by ``encode``) and in the port from the same states: the
    same actions, images and returns, episode for episode."""
    gym = pytest.importorskip("gymnasium")
    pytest.importorskip("minigrid")
    import minigrid  # noqa: F401

    from taskvar_torch.factory import load_heads, make_method_controller

    cli.main(["train", DOORKEY, "--out", str(tmp_path), *TINY])
    heads, cfg = load_heads(tmp_path / "final.pt")
    n, fam = 32, family(cfg)
    env = fam.make_env(cfg, n, instances="minigrid")
    ctrl = make_method_controller(cfg, "averaging", heads, fam.subtasks(cfg, env))
    envs = [gym.make("MiniGrid-DoorKey-5x5-v0", max_steps=40) for _ in range(n)]
    obs = [e.reset(seed=s)[0] for s, e in enumerate(envs)]
    us = [e.unwrapped for e in envs]
    env.reset()
    env.set_state(
        np.stack([u.grid.encode().reshape(-1, 3) for u in us]),
        [int(u.agent_pos[0]) for u in us],
        [int(u.agent_pos[1]) for u in us],
        [u.agent_dir for u in us],
        torch.zeros(n, 3),
        [0] * n,
    )
    ours, theirs = torch.zeros(n), torch.zeros(n)
    live = torch.ones(n, dtype=torch.bool)
    td = env._out()
    for _ in range(40):
        image = torch.stack([torch.as_tensor(o["image"]) for o in obs])
        direction = torch.tensor([o["direction"] for o in obs])
        assert torch.equal(image[live], env.image()[live])
        mg = ctrl(TensorDict({keys.OBSERVATION: encode(image, direction)}, [n]))[keys.ACTION]
        action = ctrl(td.clone())[keys.ACTION]
        assert torch.equal(mg[live], action[live])
        td = env.step(td.set(keys.ACTION, action))["next"]
        for i in live.nonzero().squeeze(-1).tolist():
            obs[i], r, term, trunc, _ = envs[i].step(int(mg[i]))
            theirs[i] += r
            ours[i] += float(td[keys.REWARD][i])
            live[i] = not (term or trunc)
        if not live.any():
            break
    assert torch.allclose(ours, theirs) and not live.any()
