"""Conv heads (``heads.network=conv``, for large grids): the grouped conv trunk of
:class:`StackedConvMLP` equals K separate convs, the patch layout matches the windy observation,
config errors, a tiny training run and its checkpoint round trip."""

from __future__ import annotations

import pytest
import torch
from budgets import SMALL  # tests/budgets.py
from tensordict import TensorDict
from torch import nn

from taskvar_torch import keys
from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.contract import PatchLayout
from taskvar_torch.factory import build_heads, load_heads, make_env, make_subtasks
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.env import observation_table
from taskvar_torch.heads.networks import StackedConvMLP, head_network
from taskvar_torch.training import train

torch.set_num_threads(1)
LARGE = "configs/windy_large.yaml"
TINY = ["heads.network=conv", "heads.conv_channels=[4, 8]", "heads.hidden=[32]", *SMALL]


def _stack(seed: int = 0) -> tuple[StackedConvMLP, PatchLayout]:
    torch.manual_seed(seed)
    patch = PatchLayout(coords_dim=2, channels=3, size=5)
    return StackedConvMLP(patch.obs_dim, (4, 6, 2), patch, (3, 5), hidden=(16,)), patch


def test_shapes_and_fused_forward_equals_each_member():
    stack, patch = _stack()
    x = torch.rand(7, patch.obs_dim)
    out = stack(x)
    assert out.shape == (3, 7, 6)
    for k, size in enumerate(stack.out_sizes):
        one = stack.forward_one(x, k)
        assert one.shape == (7, size)
        torch.testing.assert_close(out[k, :, :size], one)
    assert stack.forward_one(x.reshape(7, 1, -1), 1).shape == (7, 1, 6)  # leading batch dims kept


def test_grouped_conv_equals_k_separate_convs():
    stack, patch = _stack(seed=1)
    x = torch.rand(9, patch.obs_dim)
    feats = stack._trunk(x)  # (K, M, 2 + 5 * 25)
    for k in range(stack.num_members):
        h = x[:, 2:].reshape(9, 3, 5, 5)
        for w, b in zip(stack.conv_weights, stack.conv_biases):  # member k's own nn.Conv2d
            own = nn.Conv2d(w.shape[2], w.shape[1], 3, padding=1)
            with torch.no_grad():
                own.weight.copy_(w[k])
                own.bias.copy_(b[k])
            h = torch.relu(own(h))
        expected = torch.cat([x[:, :2], h.flatten(1)], dim=-1)
        torch.testing.assert_close(feats[k], expected)
    # a gradient through one member's output reaches only that member's conv group
    stack.forward_one(x, 1).sum().backward()
    g = stack.conv_weights[0].grad  # (K, 3, 3, 3, 3)
    assert g[1].abs().sum() > 0 and g[0].abs().sum() == 0 and g[2].abs().sum() == 0


def test_patch_layout_matches_the_windy_observation():
    layout = windy.make_layout(9, 9, num_exits=2)
    r = 2
    table = torch.as_tensor(observation_table(layout, "coords_patch", r))
    patch = PatchLayout(coords_dim=2, channels=3, size=2 * r + 1)
    assert table.shape[-1] == patch.obs_dim
    planes = table[:, 2:].reshape(-1, 3, 5, 5)  # how StackedConvMLP reads it
    for cell in range(81):
        row, col = divmod(cell, 9)
        for i in range(5):
            for j in range(5):
                rr, cc = row + i - r, col + j - r
                ch = layout.rows[rr][cc] if 0 <= rr < 9 and 0 <= cc < 9 else "#"
                assert planes[cell, :, i, j].tolist() == [ch == "#", ch == "W", ch == "G"]
    assert planes[:, 1].any() and planes[:, 2].any()  # the wind and goal planes are exercised


def test_inconsistent_patch_layout_is_an_error():
    with pytest.raises(ValueError, match="observation has 50 values"):
        StackedConvMLP(50, (2,), PatchLayout(coords_dim=2, channels=3, size=5))


@pytest.mark.parametrize(
    "config, overrides, parts",
    [
        (LARGE, ["heads.network=cnn"], ["heads.network must be one of", "'conv'", "'mlp'"]),
        ("configs/windy.yaml", ["heads.network=conv"], ["heads.network='conv'", "coords_patch"]),
        ("configs/wargus.yaml", ["heads.network=conv"], ["heads.network='conv'", "windy"]),
        (LARGE, ["heads.network=conv", "heads.conv_channels=[8, 0]"], ["heads.conv_channels[1]"]),
    ],
)
def test_bad_network_config_is_a_one_line_error(config, overrides, parts):
    with pytest.raises(ValueError) as info:
        load_config(config, overrides)
    msg = str(info.value)
    assert "\n" not in msg and all(p in msg for p in parts), msg


def test_tiny_conv_training_run_and_checkpoint_round_trip(tmp_path):
    cfg = load_config(LARGE, TINY)
    env = make_env(cfg, num_envs=1)
    torch.manual_seed(cfg.seed)
    fresh = build_heads(cfg, env, make_subtasks(cfg, env))
    stack = head_network(fresh.heads["averaging"]).stack
    assert isinstance(stack, StackedConvMLP) and stack.patch.size == 5

    train(cfg, tmp_path, progress=False)
    bundle = load_checkpoint(tmp_path / "final.pt")
    heads, cfg2 = load_heads(tmp_path / "final.pt")
    assert cfg2 == cfg and cfg2.heads.network == "conv"
    saved = bundle["models"]["heads"]
    for name, t in heads.state_dict().items():
        assert torch.equal(t, saved[name]), name
    conv_keys = [n for n in saved if "conv_weights" in n]
    assert conv_keys and any(  # the conv trunk was trained, not left at its initial weights
        not torch.equal(saved[n], fresh.state_dict()[n]) for n in conv_keys
    )
    obs = env.reset()[keys.OBSERVATION]
    td = heads(TensorDict({keys.OBSERVATION: obs.reshape(1, -1)}, [1]))
    assert td[keys.ACTION_VALUE].shape == (1, 4) and td[keys.OPTION_ACTION_VALUE].shape == (1, 2, 4)
    assert (td[keys.MAX_VALUE] >= td[keys.OPTION_VALUE]).all()


def test_conv_stack_has_no_snapshots():
    """Snapshots cover the MLP layers only: a conv stack refuses them."""
    stack, patch = _stack()
    with pytest.raises(NotImplementedError):
        stack.snapshot()
    with pytest.raises(NotImplementedError):
        stack.forward_snapshots(torch.zeros(2, patch.obs_dim), stack.parameters())
    x = torch.zeros(2, patch.obs_dim)  # the live weights: forward, one group
    assert torch.equal(stack.forward_snapshots(x)[0], stack(x))
