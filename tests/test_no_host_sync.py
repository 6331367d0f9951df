"""No host round trips in the batched step (docs/design.md, Randomness).

Without a GPU, the pure step functions are run on the ``meta`` device: meta tensors have shapes
and dtypes but no data, so any host synchronisation hidden in a step (``.item()``, ``bool(t)``,
``.tolist()``, data-dependent shapes such as ``nonzero`` or boolean-mask indexing) raises instead
of silently copying to the host. On CUDA the same property is checked by
``torch.cuda.set_sync_debug_mode("error")`` in ``benchmarks/no_host_sync.py`` (env steps,
controllers' batched decisions, learner updates; exits 1 on a sync), which
``tests/test_benchmarks.py`` runs with ``--quick``: the real check where a GPU is lent, a skip
line without one.
"""

from __future__ import annotations

import copy

import pytest
import torch

from taskvar_torch import rng
from taskvar_torch.families.wargus import WargusEnv
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.windy import WindyGridEnv
from taskvar_torch.families.windy import dynamics as windy


def on_meta(model):
    """A shallow copy of a family model with every tensor attribute moved to ``meta``."""
    m = copy.copy(model)
    for name, value in vars(model).items():
        if isinstance(value, torch.Tensor):
            setattr(m, name, value.to("meta"))
    return m


def test_meta_catches_a_host_sync():
    """The probe itself can fail: a step that reads a value on the host raises on meta."""
    x = torch.zeros(4, dtype=torch.int64, device="meta")
    with pytest.raises((RuntimeError, NotImplementedError)):
        bool((x > 0).any())
    with pytest.raises((RuntimeError, NotImplementedError)):
        x[x > 0]


@pytest.mark.parametrize("layout", ["default", "whole_column_windy"])
def test_windy_step_and_gusts_have_no_host_sync(layout):
    model = on_meta(windy.WindyModel(windy.WindyLayout.named(layout)))
    B = 64
    meta = dict(device="meta", dtype=torch.int64)
    cell, action, direction = (torch.empty(B, **meta) for _ in range(3))
    key = torch.empty(B, **meta)
    gust = rng.draw_uniform(key, torch.empty(B, **meta)) < torch.empty(B, device="meta")
    nxt, terminated = windy.step(model, cell, action, direction, gust)
    assert nxt.device.type == "meta" and nxt.shape == (B,)
    assert terminated.dtype == torch.bool and terminated.shape == (B,)


@pytest.mark.parametrize("hit_prob,patrol_speed", [(1.0, 0.8), (0.5, 1.0)])
def test_wargus_reset_step_observe_have_no_host_sync(hit_prob, patrol_speed):
    cfg = wargus.WargusConfig(
        size=16, num_patrols=3, num_items=2, hit_prob=hit_prob, patrol_speed=patrol_speed
    )
    model = on_meta(wargus.WargusModel(cfg))
    B = 32
    key = torch.empty(B, device="meta", dtype=torch.int64)
    state = wargus.reset(model, key)
    obs, item_seen, _ = wargus.observe(model, state)
    action = torch.empty(B, device="meta", dtype=torch.int64)
    state, picked, destroyed = wargus.step(model, state, action, key)
    obs2, item_seen2, _ = wargus.observe(model, state)
    lost = wargus.item_lost(item_seen, item_seen2, picked)
    assert obs2.shape == (B, wargus.OBS_DIM) and destroyed.shape == (B,) and lost.shape == (B,)
    assert state.agent.device.type == "meta"


def test_action_validation_defaults_to_cpu_only():
    """The env wrappers' range check syncs, so by default it runs on CPU only (no host
    round trip in an accelerator step); it can be forced either way."""

    for cls in (WindyGridEnv, WargusEnv):
        assert cls(num_envs=2, seed=0).validate_actions
        assert not cls(num_envs=2, seed=0, validate_actions=False).validate_actions
        td = cls(num_envs=2, seed=0).reset()
        td["action"] = torch.tensor([0, 99])
        with pytest.raises(ValueError, match="action"):
            cls(num_envs=2, seed=0).step(td)
