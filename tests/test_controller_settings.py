"""Controller settings at evaluation (config/controller.py, issue 46 item 4): ``taskvar eval``
plays a bundle with other ``train.*`` controller settings without retraining, records them in
``metrics.json``, and refuses a key that is not a controller setting in one line."""

from __future__ import annotations

import json

import pytest
import torch

from taskvar_torch.cli import main
from taskvar_torch.cli.study import _check_checkpoint_overrides
from taskvar_torch.config import load_config
from taskvar_torch.config.controller import CONTROLLER_KEYS, with_controller_settings
from taskvar_torch.experiments.bundle_eval import eval_bundle
from taskvar_torch.factory import load_heads
from taskvar_torch.training import train

torch.set_num_threads(1)
TINY = [
    "env.num_envs=4",
    "env.wargus.size=12",
    "env.wargus.horizon=40",
    "train.frames_per_batch=100",
    "train.total_frames=200",
    "train.checkpoint_every=0",
    "train.log_every=200",
    "train.init_random_frames=100",
    "train.batch_size=16",
    "train.updates_per_batch=1",
    "train.buffer_size=1000",
    "train.compile=false",
]


@pytest.fixture(scope="module")
def wargus(tmp_path_factory):
    """A tiny Wargus bundle: a composition hierarchy (TG+FE over TG, FE) and robustness critics."""
    out = tmp_path_factory.mktemp("wargus")
    train(load_config("configs/wargus.yaml", TINY), out, progress=False)
    return out / "final.pt"


def _root_share(checkpoint, settings):
    m = eval_bundle(checkpoint, "hierarchy", episodes=8, progress=False, controller=settings)
    return m["control"]["TG+FE"], m


def test_a_threshold_changed_at_evaluation_changes_who_acts(wargus):
    """tau below every robustness value keeps the root in control on every step; above every
    value it never holds control (Algorithm 2 descends to a component at once): the same heads,
    two settings, two different controllers."""
    low, m_low = _root_share(
        wargus, ["train.robustness_threshold=fixed", "train.robustness_tau=-1e9"]
    )
    high, m_high = _root_share(
        wargus, ["train.robustness_threshold=fixed", "train.robustness_tau=1e9"]
    )
    assert low == 1.0 and high == 0.0
    assert m_low["controller"]["train.robustness_tau"] == -1e9
    assert m_high["controller_overrides"] == [
        "train.robustness_threshold=fixed",
        "train.robustness_tau=1e9",
    ]
    _, m_own = _root_share(wargus, [])  # the bundle's own settings, recorded as such
    assert m_own["controller"]["train.robustness_threshold"] == "calibrated"
    assert m_own["controller_overrides"] == []


def test_the_command_line_takes_settings_and_writes_them(wargus, tmp_path, capsys):
    out = tmp_path / "eval"
    argv = ["eval", "--checkpoint", str(wargus), "--method", "hierarchy", "--episodes", "4"]
    assert main([*argv, "--out", str(out), "--no-progress", "train.hierarchy_descent=raw"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["controller"]["train.hierarchy_descent"] == "raw"
    assert set(metrics["controller"]) == set(CONTROLLER_KEYS)


@pytest.mark.parametrize(
    "item, match",
    [
        ("train.lr=0.1", r"'train\.lr' is not a controller setting.*train\.robustness_threshold"),
        ("env.wargus.size=20", r"not a controller setting \(an env key .*--shift"),
        ("train.robustness_threshold=sometimes", r"train\.robustness_threshold must be one of"),
        ("train.robustness_tau", r"expected a controller setting key=value"),
    ],
)
def test_a_key_that_is_not_a_controller_setting_is_one_line(wargus, capsys, item, match):
    import re

    argv = ["eval", "--checkpoint", str(wargus), "--method", "hierarchy", "--episodes", "2", item]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(match, err), err


def test_settings_reach_mu_bar_and_the_experiment_split():
    cfg = load_config("configs/windy.yaml")
    soft = with_controller_settings(cfg, ["train.mu_bar=softmax", "train.mu_bar_temperature=0.5"])
    assert soft.train.mu_bar == "softmax" and soft.env == cfg.env and soft.heads == cfg.heads
    kept, ctrl = _check_checkpoint_overrides(["eval.episodes=10", "train.mu_bar=softmax"])
    assert kept == ["eval.episodes=10"] and ctrl == ["train.mu_bar=softmax"]
    with pytest.raises(ValueError, match="cannot apply with --checkpoint.*controller settings"):
        _check_checkpoint_overrides(["train.lr=0.1"])


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_load_heads_and_the_experiment_build_mu_bar_from_the_settings(tmp_path):
    cfg = load_config("configs/windy.yaml", TINY[:1] + TINY[3:])
    train(cfg, tmp_path / "run", progress=False)
    bundle = tmp_path / "run" / "final.pt"
    heads, _ = load_heads(bundle)
    assert heads.softmax_temperature is None  # the bundle's greedy mu_bar
    soft = ["train.mu_bar=softmax", "train.mu_bar_temperature=0.25"]
    heads, c = load_heads(bundle, controller=soft)
    assert heads.softmax_temperature == 0.25 and c.train.mu_bar == "softmax"
    out = tmp_path / "fig2"  # experiment windy-fig2 --checkpoint plays them, config.yaml says so
    sizes = ["experiment.runs=1", "experiment.episodes_per_run=8", "eval.batch_size=8"]
    argv = ["experiment", "windy-fig2", "--checkpoint", str(bundle), "--out", str(out)]
    assert main([*argv, *sizes, *soft, "--no-progress", "--no-plots"]) == 0
    played = load_config(out / "config.yaml")
    assert played.train.mu_bar == "softmax" and played.train.mu_bar_temperature == 0.25


def test_a_family_naming_no_conflict_states_keeps_the_fixed_threshold_at_its_root():
    """Subtasks.no_conflict is None by default: a calibrated composed subtask then keeps
    train.robustness_tau (calibrated on every state it would hold control on the keep share of
    them, whatever its policy is worth); the leaves are calibrated as before."""
    from taskvar_torch.heads.robustness import calibrate_robustness
    from taskvar_torch.subtasks.base import Subtasks

    g = torch.Generator().manual_seed(0)
    r = torch.randn(1000, 3, generator=g) + torch.tensor([0.0, 1.0, -5.0])
    startable = torch.ones(1000, 3, dtype=torch.bool)
    composed = torch.tensor([False, False, True])
    cal = calibrate_robustness(r, startable, None, composed, keep_share=0.9, default_tau=2.0)
    assert float(cal.tau[2]) == 2.0  # the root: the fixed threshold
    assert float(cal.tau[0]) == pytest.approx(float(torch.quantile(r[:, 0], 0.1)))
    every = calibrate_robustness(
        r, startable, torch.ones(1000, dtype=torch.bool), composed, 0.9, 2.0
    )
    assert float((r[:, 2] > every.tau[2]).float().mean()) == pytest.approx(0.9, abs=0.01)
    assert Subtasks().no_conflict(None) is None
