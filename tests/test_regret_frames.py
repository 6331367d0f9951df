"""Regret against training frames (issue 31, item 3; docs/memory.md "Regret against training
frames"): ``experiments/regret_frames.py`` and ``taskvar eval --by-frames`` give each memoryless
method's exact regret against the exact per-instance optimum on every ``train.heads_every``
snapshot of a run and on its final heads, on the same paired episodes as ``taskvar eval``."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest
import torch

from taskvar_torch.cli import main
from taskvar_torch.config import load_config
from taskvar_torch.experiments.bundle_eval import eval_bundle
from taskvar_torch.experiments.paired import point_oracle
from taskvar_torch.experiments.regret_frames import (
    CSV_NAME,
    PNG_NAME,
    check_by_frames,
    regret_by_frames,
)
from taskvar_torch.experiments.shift import shift_points
from taskvar_torch.factory import load_heads, make_env, make_method_controller, make_subtasks
from taskvar_torch.oracle.episodes import exact_episode_returns
from taskvar_torch.training import train

torch.set_num_threads(1)
CORRIDOR = "configs/windy_corridor.yaml"  # memory provably helps; 5 cells: exact values are cheap
TINY = [  # ~3 s: snapshots at 1024, 2048 and 3072 frames, final at 4096
    "train.total_frames=4096",
    "train.updates_per_batch=8",  # the shipped 32 learn no more here (the same regrets, 3x the time)
    "train.init_random_frames=1024",
    "train.eps_decay_frames=2000",
    "train.checkpoint_every=0",
    "train.log_every=4096",
    "train.heads_every=1024",
]
EPISODES = 300


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("corridor")
    train(load_config(CORRIDOR, TINY), d, progress=False)
    return d


@pytest.fixture(scope="module")
def evaluated(run, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    m = eval_bundle(
        run / "final.pt",
        "all",
        "train",
        episodes=EPISODES,
        out_dir=out,
        progress=False,
        by_frames=True,
    )
    return m, out


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_the_final_point_is_taskvar_evals_exact_regret(run, evaluated):
    """The final heads' point is what ``taskvar eval`` reports for ``final.pt`` on the same
    episodes, method by method; the snapshots come first, in frame order."""
    m, _ = evaluated
    data = m["regret_by_frames"]
    frames = [p["frames"] for p in data["points"]]
    assert frames == [1024, 2048, 3072, 4096]
    assert data["points"][-1]["bundle"] == str(run / "final.pt")
    assert data["methods"] == ["averaging", "options", "interruption"]  # the memoryless ones
    assert m["methods"] == data["methods"]  # no baseline beside this run
    per = m["points"][0]["methods"]
    assert abs(data["optimum_mean_return"] - m["points"][0]["optimum_mean_return"]) < 1e-9
    for name in data["methods"]:
        got = data["points"][-1]["methods"][name]
        assert abs(got["regret_mean"] - per[name]["regret_mean"]) < 1e-9, name
        assert abs(got["regret_ci95"] - per[name]["regret_ci95"]) < 1e-9, name
        assert abs(got["exact_mean_return"] - per[name]["exact_mean_return"]) < 1e-9, name
    # the run folder gives the same numbers (the module alone, no --out)
    alone = regret_by_frames(run, "all", "train", episodes=EPISODES)
    assert alone["points"] == data["points"] and alone["seed"] == m["seed"] == data["seed"]


def test_no_regret_beats_the_optimum_and_a_snapshot_recomputes(run, evaluated):
    """Exact values cannot beat the exact per-instance optimum; a snapshot's regret recomputed
    from eval's episodes.csv (instance, start, optimum per episode) matches: the same episodes."""
    m, out = evaluated
    data = m["regret_by_frames"]
    for p in data["points"]:
        for name, r in p["methods"].items():
            assert r["regret_mean"] >= -1e-9, (p["frames"], name)
            assert r["exact_mean_return"] <= data["optimum_mean_return"] + 1e-9
            gap = data["optimum_mean_return"] - r["exact_mean_return"]
            assert abs(gap - r["regret_mean"]) < 1e-9  # regret of the means = mean of regrets
    with open(out / "episodes.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["method"] == "averaging"]
    instance = {
        "p": np.array([float(r["instance_p"]) for r in rows]),
        "direction": np.array([int(r["instance_direction"]) for r in rows]),
    }
    start = np.array([int(r["start"]) for r in rows])
    optimum = np.array([float(r["optimum_return"]) for r in rows])
    snap = data["points"][1]["bundle"]
    heads, cfg = load_heads(snap)
    point = shift_points(cfg, "train", [])[0]
    subtasks = make_subtasks(point.cfg, make_env(point.cfg, 1))
    oracle = point_oracle(cfg, point)
    for name in data["methods"]:
        ctrl = make_method_controller(point.cfg, name, heads, subtasks)
        exact = exact_episode_returns(oracle, ctrl, point.cfg, instance, start)
        want = float(np.mean(optimum - exact))
        assert abs(want - data["points"][1]["methods"][name]["regret_mean"]) < 1e-9, name


def test_the_csv_and_plot_and_metrics(evaluated):
    """The CSV's rows are the returned numbers; metrics.json holds them under the new key beside
    every key ``taskvar eval`` writes without the flag."""
    m, out = evaluated
    data = m["regret_by_frames"]
    with open(out / CSV_NAME) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(data["points"]) * len(data["methods"])
    for row in rows:
        p = next(p for p in data["points"] if p["frames"] == int(row["frames"]))
        r = p["methods"][row["method"]]
        assert int(row["updates"]) == p["updates"]
        assert float(row["regret_mean"]) == r["regret_mean"]
        assert float(row["ci95"]) == r["regret_ci95"]
        assert (
            abs(data["optimum_mean_return"] - float(row["exact_mean_return"]) - r["regret_mean"])
            < 1e-9
        )
    assert (out / PNG_NAME).stat().st_size > 0 and data["files"] == [CSV_NAME, PNG_NAME]
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["regret_by_frames"]["points"] == data["points"]
    plain = eval_bundle(m["checkpoint"], "all", "train", episodes=5, progress=False)
    assert set(m) - set(plain) == {"regret_by_frames", "regret_by_instance", "figures"}
    assert "regret_by_frames" not in plain


def test_the_first_snapshot_loses_more_than_the_final_heads(evaluated):
    """Training helps on this tiny run: the averaging controller's regret falls from the first
    snapshot (1024 frames, 8 updates: trapped to the horizon, ~98.5) to the final heads (~1.9),
    by far more than both CIs (measured margin ~96, as with 32 updates per batch)."""
    data = evaluated[0]["regret_by_frames"]
    first, final = (data["points"][i]["methods"]["averaging"] for i in (0, -1))
    assert first["regret_mean"] - first["regret_ci95"] > final["regret_mean"] + final["regret_ci95"]
    assert first["regret_mean"] > final["regret_mean"] + 10.0


def test_by_frames_refusals_are_one_line(run, tmp_path, capsys):
    """No snapshots, a shift curve and a family without an exact oracle: one-line errors before
    any episode is played."""
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(run / "final.pt", bare / "final.pt")
    argv = ["eval", "--no-progress", "--episodes", "5", "--by-frames"]
    assert main([*argv, "--checkpoint", str(bare / "final.pt")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "train.heads_every=N" in err, err
    curve = ["--shift", "env.instances.p=0.2,0.8"]
    assert main([*argv, "--checkpoint", str(run / "final.pt"), *curve]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "one test point" in err, err
    wargus = shift_points(load_config("configs/wargus.yaml"), None, [])
    with pytest.raises(ValueError, match="families with one: .*windy") as e:
        check_by_frames(run, wargus)
    assert "\n" not in str(e.value) and "wargus" in str(e.value)


@pytest.mark.slow
def test_the_cli_flag_prints_and_writes(run, tmp_path, capsys):
    """``taskvar eval --by-frames`` (default methods: all) prints the table and writes the files."""
    out = tmp_path / "o"
    argv = ["eval", "--checkpoint", str(run / "final.pt"), "--by-frames", "--test", "train"]
    assert main([*argv, "--episodes", "40", "--no-progress", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "by training frames" in printed and "regret_by_frames.png" in printed
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["methods"] == ["averaging", "options", "interruption"]
    assert saved["regret_by_frames"]["methods"] == ["averaging", "options", "interruption"]
    assert [p["frames"] for p in saved["regret_by_frames"]["points"]] == [1024, 2048, 3072, 4096]
