"""Option heads that see their subtask's own features (``heads.option_inputs=subtask``, Wargus):
each option's policy is its own member of the stack, blind to the other subtask's features; the
fused pass equals each member's; config errors; a tiny training run and its checkpoint round trip."""

from __future__ import annotations

import pytest
import torch
from budgets import SMALL  # tests/budgets.py

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, load_heads, make_env, make_subtasks
from taskvar_torch.families.wargus.dynamics import (
    OBS_AGENT,
    OBS_ITEM_BEARING,
    OBS_ITEM_OFFSET,
    OBS_PATROL_BEARING,
    OBS_PATROL_OFFSET,
    OBS_PATROL_SEEN,
)
from taskvar_torch.heads.networks import StackedMLP, head_network
from taskvar_torch.training import train

torch.set_num_threads(1)
WARGUS = "configs/wargus.yaml"
SUBTASK = ["heads.option_inputs=subtask"]
TINY = [*SUBTASK, "heads.hidden=[32]", *SMALL]


def _heads(overrides):
    cfg = load_config(WARGUS, overrides)
    env = make_env(cfg, num_envs=1)
    torch.manual_seed(0)
    return build_heads(cfg, env, make_subtasks(cfg, env))


def test_each_option_sees_only_its_subtask_features():
    heads = _heads(SUBTASK)
    options = heads.heads["options"].module
    obs = torch.rand(5, 24)
    q = options(obs)
    assert q.shape == (5, 3, 9 if load_config(WARGUS).env.wargus.noop else 8)
    patrol = obs.clone()
    for part in (OBS_PATROL_BEARING, OBS_PATROL_OFFSET):
        patrol[:, part] += 1.0
    patrol[:, OBS_PATROL_SEEN] = 1.0 - patrol[:, OBS_PATROL_SEEN]
    item = obs.clone()
    for part in (OBS_ITEM_BEARING, OBS_ITEM_OFFSET):
        item[:, part] += 1.0
    agent = obs.clone()
    agent[:, OBS_AGENT] += 0.5
    q_patrol, q_item, q_agent = options(patrol), options(item), options(agent)
    assert torch.equal(q_patrol[:, 0], q[:, 0])  # TG is blind to the patrol
    assert torch.equal(q_item[:, 1], q[:, 1])  # FE is blind to the item
    assert not torch.allclose(q_patrol[:, 1], q[:, 1])  # FE reads the patrol
    assert not torch.allclose(q_item[:, 0], q[:, 0])  # TG reads the item
    assert not torch.allclose(q_patrol[:, 2], q[:, 2])  # the root reads everything
    assert not torch.allclose(q_item[:, 2], q[:, 2])
    assert not torch.allclose(q_agent[:, 0], q[:, 0])  # both read the agent's position
    assert not torch.allclose(q_agent[:, 1], q[:, 1])


def test_fused_pass_equals_each_head_and_full_inputs_keep_one_member():
    heads = _heads(SUBTASK)
    stack = head_network(heads.heads["options"]).stack
    assert isinstance(stack, StackedMLP) and stack.input_mask is not None
    full = head_network(_heads(["heads.option_inputs=full"]).heads["options"]).stack
    assert full.input_mask is None and stack.num_members == full.num_members + 2
    obs = torch.rand(7, 24)
    out = stack(obs)  # (K, 7, max_out)
    for name in ("averaging", "options", "switching", "robustness"):
        net = head_network(heads.heads[name])
        fused = net.select(out).reshape(7, *net.out_shape)
        torch.testing.assert_close(fused, net(obs))


def test_bad_option_inputs_are_one_line_errors():
    for config, overrides, parts in (
        (WARGUS, ["heads.option_inputs=items"], ["heads.option_inputs", "'full'", "'subtask'"]),
        ("configs/windy.yaml", SUBTASK, ["heads.option_inputs='subtask'", "exits_patch"]),
    ):
        with pytest.raises(ValueError) as info:
            load_config(config, overrides)
        msg = str(info.value)
        assert "\n" not in msg and all(p in msg for p in parts), msg


@pytest.mark.slow
def test_tiny_training_run_and_checkpoint_round_trip(tmp_path):
    cfg = load_config(WARGUS, TINY)
    env = make_env(cfg, num_envs=1)
    torch.manual_seed(cfg.seed)
    fresh = build_heads(cfg, env, make_subtasks(cfg, env))
    train(cfg, tmp_path, progress=False)
    heads, cfg2 = load_heads(tmp_path / "final.pt")
    assert cfg2.heads.option_inputs == "subtask"
    stack = head_network(heads.heads["options"]).stack
    assert stack.input_mask is not None  # rebuilt from the config, not stored
    assert "input_mask" not in " ".join(heads.state_dict())
    net = head_network(heads.heads["options"])
    trained = [stack.weights[0][net.index + j] for j in range(3)]
    before = head_network(fresh.heads["options"]).stack.weights[0]
    assert all(not torch.equal(w, before[net.index + j]) for j, w in enumerate(trained))
    obs = env.reset()[keys.OBSERVATION]
    assert heads.heads["options"].module(obs).shape[-2] == 3
