"""``taskvar eval`` on bundles of either family (experiments/bundle_eval.py, experiments/shift.py):
every method on the same paired episodes, named test distributions, shifts that reach the env,
one-line errors for bad shifts, shareable bundles (heads.pt, taskvar export)."""

from __future__ import annotations

import csv
import json

import pytest
import torch
from budgets import TINY  # tests/budgets.py

from taskvar_torch.cli import main
from taskvar_torch.config import load_config
from taskvar_torch.experiments.bundle_eval import eval_bundle, format_table
from taskvar_torch.experiments.shift import parse_shift, shift_points
from taskvar_torch.factory import export_heads, load_heads, make_env
from taskvar_torch.training import train

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def bundles(tmp_path_factory, windy_tiny_bundle):
    """Run folders: Wargus trained here, windy's shared (tests/conftest.py; read only)."""
    d = tmp_path_factory.mktemp("wargus")
    train(load_config("configs/wargus.yaml", [*TINY, "env.wargus.horizon=60"]), d, progress=False)
    return {"wargus": d, "windy": windy_tiny_bundle.parent}


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_a_wargus_bundle_evaluates_every_method_on_paired_episodes(bundles, tmp_path):
    m = eval_bundle(
        bundles["wargus"] / "final.pt",
        "all",
        "fast_patrol",
        episodes=6,
        out_dir=tmp_path,
        progress=False,
    )
    assert m["methods"] == ["averaging", "options", "interruption", "hierarchy"]
    point = m["points"][0]["methods"]
    assert set(point) == set(m["methods"]) and "control" in point["hierarchy"]
    assert abs(sum(point["hierarchy"]["control"].values()) - 1.0) < 1e-9
    assert {p.name for p in tmp_path.iterdir()} >= {"metrics.json", "episodes.csv", "eval.png"}
    rows = _rows(tmp_path / "episodes.csv")
    assert len(rows) == 4 * 6
    seeds = {}
    for r in rows:  # the same instance per episode index, whatever the method
        seeds.setdefault(r["episode"], set()).add(r["instance_seed"])
    assert all(len(s) == 1 for s in seeds.values()) and len(seeds) == 6
    assert "hierarchy" in format_table(m) and "fast_patrol" in format_table(m)


@pytest.mark.slow
def test_windy_shift_curve_with_exact_values_and_paired_instances(bundles, tmp_path):
    m = eval_bundle(
        bundles["windy"] / "final.pt",
        "all",
        "south",
        ["env.instances.p=0.0,1.0"],
        episodes=40,
        out_dir=tmp_path,
        progress=False,
    )
    # no hierarchy on windy; the informed baseline beside the bundle (tests/conftest.py)
    assert m["methods"] == ["averaging", "options", "interruption", "informed"]
    memoryless = m["methods"][:3]
    assert all("exact_mean_return" in p["methods"][k] for p in m["points"] for k in memoryless)
    assert all(p["methods"]["informed"]["regret_sampled"] for p in m["points"])
    rows = _rows(tmp_path / "episodes.csv")
    for r in rows:  # the shift reached the env: every episode's wind is the swept value
        assert float(r["instance_p"]) == float(r["shift"].split("=")[1])
        assert r["instance_direction"] == "1"  # south-only
    key = {(r["shift"], r["episode"]): set() for r in rows}
    for r in rows:
        key[(r["shift"], r["episode"])].add((r["instance_p"], r["start"]))
    assert all(len(v) == 1 for v in key.values())


def test_a_shift_changes_the_env_parameters(bundles):
    _, cfg = load_heads(bundles["wargus"] / "final.pt")
    (point,) = shift_points(cfg, "train", [parse_shift("env.wargus.patrol_speed=0.25")])
    env = make_env(point.cfg, 2, instances=point.instances)
    assert point.cfg.env.wargus.patrol_speed == 0.25 and env.config.patrol_speed == 0.25
    (named,) = shift_points(cfg, "large_grid")
    assert make_env(named.cfg, 1, instances=named.instances).config.size == 64


@pytest.mark.parametrize(
    ("shift", "part"),
    [
        ("train.lr=1", "env keys only"),
        ("env.wargus.speed=1", "env.wargus.speed"),
        ("env.wargus.patrol_speed=2", "patrol_speed"),
        ("env.instances.q=1", "instance fields"),
        ("env.wargus", "KEY=VALUE"),
    ],
)
def test_bad_shifts_are_one_line_errors(bundles, capsys, shift, part):
    argv = ["eval", "--checkpoint", str(bundles["wargus"] / "final.pt"), "--episodes", "2"]
    assert main([*argv, "--no-progress", "--shift", shift]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and part in err, err


def test_bad_test_names_and_methods_are_one_line_errors(bundles, capsys):
    windy = str(bundles["windy"] / "final.pt")
    for extra, part in (
        (["--test", "fast_patrol"], "calm"),
        (["--method", "hierarchy"], "hierarchy"),
    ):
        assert main(["eval", "--checkpoint", windy, "--no-progress", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and part in err, err


def test_shareable_bundle_beside_the_checkpoint_and_export(bundles, tmp_path, capsys):
    run = bundles["wargus"]
    shared = run / "heads.pt"
    assert shared.is_file() and shared.stat().st_size < (run / "final.pt").stat().st_size
    a, _ = load_heads(run / "final.pt")
    b, cfg = load_heads(shared)
    obs = torch.rand(3, 24)
    assert torch.equal(a.heads["options"].module(obs), b.heads["options"].module(obs))
    with pytest.raises(ValueError, match="exists"):
        export_heads(run / "final.pt")
    assert main(["export", str(run / "final.pt"), "--out", str(tmp_path / "h.pt")]) == 0
    assert "wrote" in capsys.readouterr().out
    m = eval_bundle(tmp_path / "h.pt", "averaging", episodes=3, progress=False)
    json.dumps(m)
    assert m["method"] == "averaging" and "mean_return" in m


def test_returns_change_where_the_shift_must_change_them(bundles):
    m = eval_bundle(
        bundles["windy"] / "final.pt",
        "averaging",
        shifts=["env.windy.horizon=7,300"],
        episodes=20,
        progress=False,
    )
    short, long = (p["methods"]["averaging"] for p in m["points"])
    assert short["mean_length"] <= 7 and short["mean_return"] >= -7  # the horizon reached the env
    assert short["exact_mean_return"] >= -7.0 - 1e-9  # exact: a 7-step episode costs at most 7
    # paired episodes, -1 per step: a longer horizon can only add cost
    assert (
        long["mean_return"] <= short["mean_return"] and long["mean_length"] >= short["mean_length"]
    )


@pytest.mark.slow
def test_eval_refuses_a_folder_holding_results_and_checks_points_first(bundles, tmp_path, capsys):
    ckpt = str(bundles["windy"] / "final.pt")
    argv = [
        "eval",
        "--checkpoint",
        ckpt,
        "--episodes",
        "3",
        "--no-progress",
        "--out",
        str(tmp_path),
    ]
    assert main(argv) == 0
    before = (tmp_path / "metrics.json").read_text()
    assert main([*argv, "--method", "averaging"]) == 2  # no silent replacement
    assert "--overwrite" in capsys.readouterr().err
    assert (tmp_path / "metrics.json").read_text() == before
    assert main([*argv, "--method", "averaging", "--overwrite"]) == 0
    # a sweep whose second point does not fit the bundle fails before any episode is played
    bad = ["--shift", "env.windy.obs_encoding=onehot,coords_patch", "--episodes", "100000"]
    assert main(["eval", "--checkpoint", ckpt, "--no-progress", *bad]) == 2
    assert "trained on" in capsys.readouterr().err


def test_the_table_names_fixed_shifts(bundles):
    m = eval_bundle(
        bundles["windy"] / "final.pt",
        "averaging",
        "north",
        ["env.instances.p_high=0.5"],
        episodes=2,
        progress=False,
    )
    assert "shifted: env.instances.p_high=0.5" in format_table(m)


def test_the_table_labels_a_baseline_trained_on_another_budget():
    """A baseline of another training budget than the heads' is named with it under the table
    (docs/memory.md, Budgets), one of the same budget is not."""
    from taskvar_torch.experiments.bundle_eval import format_table

    row = {"mean_return": 1.0, "mean_return_ci95": 0.1}
    metrics = {
        "family": "taxi",
        "checkpoint": "b/final.pt",
        "test": "train",
        "test_description": "d",
        "episodes": 10,
        "seed": 1,
        "shifts": [],
        "points": [{"shift": "", "methods": {m: row for m in ("averaging", "informed", "blind")}}],
        "baseline_frames": {"informed": 900_000, "blind": 300_000},
        "heads_frames": 300_000,
    }
    text = format_table(metrics)
    assert "(trained on another budget than the heads' 300,000 frames: informed 900,000)" in text
    del metrics["baseline_frames"]
    assert "another budget" not in format_table(metrics)
