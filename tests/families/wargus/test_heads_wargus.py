"""Wargus robustness critics after a short training run rank states as the paper intends
(paper §3.4.3, §3.5.2): R(TG) is higher where the item is seen, R(FE) is lower inside
the patrol's sight. States come from fresh random-policy episodes (not the training data)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.factory import load_heads, make_env
from taskvar_torch.families.wargus.dynamics import ITEM_SEEN, PATROL_SEEN
from taskvar_torch.training import train

torch.set_num_threads(1)
pytestmark = pytest.mark.slow

SHORT = [
    "env.wargus.size=16",
    "env.wargus.horizon=100",
    "train.total_frames=20000",
    "train.init_random_frames=2000",
    "train.eps_decay_frames=10000",
    "train.buffer_size=50000",
    "train.checkpoint_every=0",
    "train.compile=false",  # configs/wargus.yaml compiles; a test run does not pay it off
]


@pytest.fixture(scope="module")
def robustness(tmp_path_factory):
    cfg = load_config("configs/wargus.yaml", SHORT)
    result = train(cfg, tmp_path_factory.mktemp("wargus_heads"), progress=False)
    heads, cfg = load_heads(result["final"])
    env = make_env(dataclasses.replace(cfg, seed=cfg.seed + 1000), num_envs=32)
    td = env.rollout(100, break_when_any_done=False).reshape(-1)  # random actions, new episodes
    with torch.no_grad():
        out = heads(td.select(keys.OBSERVATION).clone())
    pi = out[keys.OPTION_ACTION_VALUE].argmax(-1, keepdim=True)  # (B, O, 1) option actions
    r = out[keys.ROBUSTNESS].gather(-1, pi).squeeze(-1)  # (B, O) R(o, s, pi^o(s))
    names = heads.option_names
    return {name: r[:, k] for k, name in enumerate(names)}, td


def test_robustness_tg_higher_where_item_seen(robustness):
    r, td = robustness
    seen = td[ITEM_SEEN]
    assert 100 < seen.sum() < seen.numel() - 100  # both kinds of state are present
    assert r["TG"][seen].mean() > r["TG"][~seen].mean() + 0.3


def test_robustness_fe_lower_inside_patrol_sight(robustness):
    r, td = robustness
    inside = td[PATROL_SEEN]
    assert 30 < inside.sum() < inside.numel() - 30
    assert r["FE"][inside].mean() < r["FE"][~inside].mean() - 0.2
