"""Scaled-up grids experiment: CLI --quick run on tiny budgets, metrics, config, plot."""

from __future__ import annotations

import csv
import json
import math

import pytest
import torch

from taskvar_torch.cli import main
from taskvar_torch.config import METHODS
from taskvar_torch.study import scale, scale_config, scale_eval

torch.set_num_threads(1)

NUM_ENVS = (4, 8)
TINY = [  # --quick, reduced further: two small cases, a few hundred frames, 16 test episodes
    "total_frames=600",
    f"num_envs=[{','.join(map(str, NUM_ENVS))}]",
    "eval_episodes=16",
    "eval_batch_size=8",
    "only=[windy-5x5,wargus-32x32]",
    "curve_points=3",
    "curve_episodes=8",
    'overrides=[env.wargus.size=12,env.wargus.horizon=40,"heads.hidden=[32]",train.batch_size=32]',
]
FILES = ("config.yaml", "scale.csv", "metrics.json", "scale.png", "scale_curves.png")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("scale")
    assert main(["experiment", "scale", "--quick", "--out", str(out), "--no-progress", *TINY]) == 0
    return out, json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
def test_quick_run_writes_files_and_sane_metrics(quick_run):
    out, m = quick_run
    for name in FILES:
        assert (out / name).is_file(), name
    assert not list(out.glob("cells/*/final.pt"))  # keep_checkpoints=false
    assert m["experiment"] == "scale" and m["quick"] is True
    assert set(m["references"]) == {"windy-5x5", "wargus-32x32"}
    assert len(m["cells"]) == 2 * len(NUM_ENVS)
    assert sorted({c["num_envs"] for c in m["cells"]}) == list(NUM_ENVS)
    for c in m["cells"]:
        assert c["frames"] >= 600 and c["updates"] > 0
        assert c["train_seconds"] > 0 and c["frames_per_second"] > 0
        assert c["frames_per_batch"] % c["num_envs"] == 0
        assert (out / "cells" / f"{c['case']}-n{c['num_envs']}" / "config.yaml").is_file()
        horizon = 100 if c["family"] == "windy" else 40
        for method in METHODS:
            r = c["methods"][method]
            if c["family"] == "windy" and method == "hierarchy":
                assert r is None  # no composition hierarchy in the windy family: n/a
                continue
            assert r["episodes"] == 16
            assert math.isfinite(r["ci95"]) and r["ci95"] >= 0
            if c["family"] == "windy":
                assert -horizon <= r["mean_return"] <= -1  # -1 per step, start is never the goal
                assert math.isfinite(r["gap_closed"])
            else:
                assert 0 <= r["mean_return"] <= horizon  # items per episode
                assert r["gap_closed"] is None  # no oracle for Wargus
        assert c["grid_side"] == (5 if c["family"] == "windy" else 12)
    peaks = [c["peak_rss_mb"] for c in m["cells"]]  # the process's high-water mark after each cell
    assert peaks == sorted(peaks) and peaks[0] > 50
    assert all(c["peak_cuda_mb"] is None for c in m["cells"])  # CPU cells
    for c in m["cells"]:  # learning curves: snapshots before the end, then the final evaluation
        frames = [p["frames"] for p in c["curve"]]
        assert len(frames) >= 2 and frames == sorted(set(frames)) and frames[-1] == c["frames"]
        assert all(p["seconds"] > 0 for p in c["curve"])
        assert c["curve"][-1]["methods"]["averaging"]["mean_return"] == pytest.approx(
            c["methods"]["averaging"]["mean_return"]
        )
        assert not list((out / "cells" / f"{c['case']}-n{c['num_envs']}").glob("heads/*.pt"))
        if c["family"] == "windy":  # every head against the exact optimum
            h = c["heads"]
            assert h["averaging"]["optimum"] <= 0 and math.isfinite(h["averaging"]["rel_gap"])
            assert set(h["options"]) == {"exit_north", "exit_south"}
            assert 0 <= h["mu_bar"]["start_agreement"] <= 1
            assert 0 <= h["interruption_condition"]["agreement"] <= 1
            ic = h["interruption_controller"]
            assert -100 <= ic["expected_return"] <= -1 and ic["interruptions_per_episode"] >= 0
            if ic["interruptions_per_episode"] == 0:  # never fires: the plain options controller
                assert ic["expected_return"] == pytest.approx(
                    h["options_controller"]["expected_return"], abs=1e-9
                )
        else:
            assert c["heads"] is None
    w = m["references"]["windy-5x5"]
    assert w["oracle_averaging"]["mean_return"] > w["random"]["mean_return"]  # optimum beats random
    assert m["references"]["wargus-32x32"]["oracle_averaging"] is None
    with open(out / "scale.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(m["cells"]) * len(METHODS)
    assert {
        r["mean_return"] for r in rows if r["case"] == "windy-5x5" and r["method"] == "hierarchy"
    } == {"n/a"}


@pytest.mark.slow
def test_plot_regenerates_figure(quick_run, capsys):
    out, _ = quick_run
    (out / "scale.png").unlink()
    assert main(["plot", str(out)]) == 0
    assert (out / "scale.png").is_file()
    assert "scale.png" in capsys.readouterr().out


def test_evaluation_is_paired_and_deterministic():
    cfg = scale.load_scale_config(scale.default_config_path(), ["only=[windy-5x5]"])
    ccfg = scale_config.case_config(cfg, cfg.selected()[0], 4)
    a = scale_eval.evaluate(ccfg, "random", 12, 5)
    assert scale_eval.evaluate(ccfg, "random", 12, 5) == a  # seeded: the same numbers again
    o = scale_eval.evaluate(ccfg, "oracle_averaging", 12, 6)
    # the envs are seeded per sub-environment: batching does not change the episodes
    assert scale_eval.evaluate(ccfg, "oracle_averaging", 12, 12) == o
    assert o["mean_return"] > a["mean_return"]


@pytest.mark.slow
def test_case_config_keeps_updates_per_frame():
    cfg = scale.load_scale_config(
        scale.default_config_path(), ["total_frames=100000", "updates_per_frame=null"]
    )
    case = next(c for c in cfg.cases if c.name == "windy-25x25")  # its own: 8 per 1024 frames
    for n in (16, 48, 2048):
        c = scale_config.case_config(cfg, case, n)
        t = c.train
        assert c.env.num_envs == n and t.frames_per_batch % n == 0
        assert t.total_frames == 100000 and t.eps_decay_frames == 50000
        assert t.init_random_frames == 10000 and t.checkpoint_every == 0
        assert t.updates_per_batch / t.frames_per_batch == pytest.approx(8 / 1024, rel=0.1)
    cfg = scale.load_scale_config(scale.default_config_path(), ["updates_per_frame=0.0625"])
    for n in (16, 48):
        t = scale_config.case_config(cfg, case, n).train
        assert t.updates_per_batch / t.frames_per_batch == pytest.approx(1 / 16, rel=0.1)


@pytest.mark.parametrize(
    "override, match",
    [
        ("totl_frames=5", "totl_frames"),
        ("num_envs=[a]", "num_envs"),
        ("only=[nope]", "only must name cases"),
        ("eps_decay_fraction=2", "eps_decay_fraction"),
        ("updates_per_frame=0", "updates_per_frame"),
        ("overrides=[train.lrr=1]", "train.lrr"),
    ],
)
def test_strict_config_errors(override, match):
    with pytest.raises(ValueError, match=match):
        scale.load_scale_config(scale.default_config_path(), [override])


def test_cli_rejects_checkpoint(tmp_path, capsys):
    assert main(["experiment", "scale", "--checkpoint", "x.pt", "--out", str(tmp_path)]) == 2
    assert "--checkpoint is not used" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_threads(tmp_path, capsys):
    """--threads N sets the torch threads the cells train with (recorded in metrics.json); bad
    values and wargus-fig4 (one thread per --workers process) are refused."""
    try:
        out = tmp_path / "t2"
        args = ["experiment", "scale", "--quick", "--threads", "2", "--out", str(out)]
        one_cell = [*TINY, "only=[windy-5x5]", f"num_envs=[{NUM_ENVS[0]}]"]
        assert main([*args, "--no-progress", "--no-plots", *one_cell]) == 0
        assert json.loads((out / "metrics.json").read_text())["threads"] == 2
    finally:
        torch.set_num_threads(1)
    assert main(["experiment", "scale", "--threads", "0", "--out", str(tmp_path / "t0")]) == 2
    assert "--threads must be in [1, " in capsys.readouterr().err
    assert main(["experiment", "wargus-fig4", "--threads", "2", "--out", str(tmp_path / "w")]) == 2
    assert "use --workers N" in capsys.readouterr().err
