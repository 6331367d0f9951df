"""Wargus Figure 4 (lifelong protocol): CLI smoke run, metrics, seeds, statistics, batching."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from budgets import FIG4  # tests/budgets.py
from torchrl.envs import InitTracker, TransformedEnv

from taskvar_torch import keys
from taskvar_torch.cli import main
from taskvar_torch.config import METHODS, load_config
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.experiments import curves
from taskvar_torch.experiments.evaluation import run_episodes
from taskvar_torch.factory import load_heads, make_env, make_subtasks
from taskvar_torch.families.wargus import (
    fig4,
    fig4_agent,
    fig4_metrics,
    fig4_repetition,
    fig4_report,
    fig4_trial,
)
from taskvar_torch.families.wargus.dynamics import WargusInstances
from taskvar_torch.families.wargus.env import WargusEnv

torch.set_num_threads(1)

REPS, TRIALS = 2, 3
TINY = [
    "env.wargus.size=12",
    "env.wargus.horizon=60",
    f"experiment.runs={REPS}",
    f"experiment.trials={TRIALS}",
    *FIG4,
]
FILES = (
    "config.yaml",
    "per_trial.csv",
    "metrics.json",
    "fig4.png",
    "rep0/final.pt",
    "rep1/final.pt",
)
METHOD_KEYS = (
    "final_score",
    "final_score_std",
    "trials_to_90pct",
    "reached_90pct",
    "trials_to_90pct_per_rep",
    "interruptions_per_episode",
    "curve_mean",
    "curve_std",
    "curve_smoothed",
    "curve_per_rep",
)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = tmp_path_factory.mktemp("fig4")
    status = main(["experiment", "wargus-fig4", "--out", str(out), "--no-progress", *TINY])
    assert status == 0
    return out


def test_cli_run_writes_every_file(results):
    for name in FILES:
        assert (results / name).is_file(), name
    rows = list(csv.DictReader((results / "per_trial.csv").open()))
    assert len(rows) == REPS * TRIALS * len(METHODS)
    assert set(rows[0]) == set(fig4_report.CSV_FIELDS)
    assert {r["method"] for r in rows} == set(METHODS)
    heads, cfg = load_heads(results / "rep1" / "final.pt")  # a bundle `taskvar eval` can read
    assert heads.has("robustness") and cfg.seed == 1  # repetition 1's own seed


def test_metrics_have_every_method_and_key(results):
    m = json.loads((results / "metrics.json").read_text())
    assert m["experiment"] == fig4_metrics.EXPERIMENT
    assert set(m["methods"]) == set(METHODS)
    for name, s in m["methods"].items():
        for key in METHOD_KEYS:
            assert key in s, (name, key)
        assert 1 <= s["trials_to_90pct"] <= TRIALS
        assert math.isfinite(s["final_score"]) and s["final_score"] >= 0
        assert len(s["curve_mean"]) == len(s["curve_std"]) == TRIALS
        assert np.all(np.isfinite(s["curve_mean"])) and min(s["curve_mean"]) >= 0
        assert np.asarray(s["curve_per_rep"]).shape == (REPS, TRIALS)
    trace = m["hierarchy_trace"]["all_trials"]
    assert set(trace["per_subtask"]) == {"TG", "FE", "TG+FE"}
    assert set(trace["per_level"]) == {"level_0", "level_1"}
    assert trace["steps"] > 0
    assert sum(trace["per_subtask"].values()) == pytest.approx(1.0)
    assert m["timing"]["wall_seconds"] > 0
    cpu = m["timing"]["cpu_seconds_per_trial"]  # where a trial's CPU goes
    assert list(cpu) == list(fig4_repetition.PHASES)
    assert all(v >= 0 for v in cpu.values())
    assert cpu["learning_loop"] > 0 and cpu["test"] > 0
    assert m["protocol"]["seeds"] == [0, 1]


def test_plot_command_redraws_the_figure(results, capsys):
    (results / "fig4.png").unlink()
    assert main(["plot", str(results)]) == 0
    assert (results / "fig4.png").is_file()
    assert "fig4.png" in capsys.readouterr().out


def test_repetitions_differ_and_same_seed_reproduces(results, tmp_path):
    m = json.loads((results / "metrics.json").read_text())
    learn = m["learning_items"]["curve_per_rep"]
    frames = m["timing"]["frames_per_repetition"]
    assert learn[0] != learn[1] or frames[0] != frames[1]  # distinct seeds, distinct streams
    w0 = torch.load(results / "rep0" / "final.pt", weights_only=True)["models"]["heads"]
    w1 = torch.load(results / "rep1" / "final.pt", weights_only=True)["models"]["heads"]
    assert any(not torch.equal(w0[k], w1[k]) for k in w0)

    cfg = load_config(results / "config.yaml")
    again = fig4_repetition.run_repetition(
        cfg, 1, tmp_path
    )  # repetition 1 alone, in a fresh process state
    for i, name in enumerate(METHODS):
        assert again["items"][:, i].tolist() == m["methods"][name]["curve_per_rep"][1]
    assert again["learn_items"].tolist() == learn[1]
    assert int(again["frames"].sum()) == frames[1]


def test_side_by_side_equals_each_controller_alone():
    cfg = load_config(fig4.default_config_path(), [*TINY, "env.wargus.size=16"])
    env = TransformedEnv(make_env(cfg, num_envs=4, seed=3), InitTracker())
    torch.manual_seed(3)
    agent = fig4_agent.make_agent(cfg, env, seed=3)
    controllers = fig4_agent.make_test_controllers(agent)
    k = 3

    def nominal_env(n: int, primer) -> TransformedEnv:
        base = WargusEnv(
            n,
            config=dataclasses.asdict(cfg.env.wargus),
            instances=WargusInstances(seeds=fig4_trial.nominal_seeds(k)),
            seed=0,
        )
        return TransformedEnv(base, primer)

    primer = controllers[-1].primer
    trace = ("action", ("next", "running_option"))
    together = run_episodes(
        nominal_env(len(controllers) * k, primer()), SideBySide(controllers, k), 40, trace
    )
    for i, c in enumerate(controllers):
        alone = run_episodes(nominal_env(k, primer()), c, 40, trace if c.stateful else trace[:1])
        rows = together[i * k : (i + 1) * k]
        T = alone["trace", "alive"].shape[-1]
        for key in ("return", "length", ("trace", "action"), ("trace", "alive")):
            got = rows[key] if key[0] != "trace" else rows[key][:, :T]
            torch.testing.assert_close(got, alone[key], msg=f"{c.name}: {key}")
        if c.stateful:
            key = ("trace", "next", "running_option")
            torch.testing.assert_close(rows[key][:, :T], alone[key], msg=c.name)
    assert together["length"].sum() > len(controllers) * k  # episodes last several steps


def test_moving_average_matches_a_loop():
    x = np.array([3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0])
    w = 3
    loop = [x[max(0, t - w + 1) : t + 1].mean() for t in range(x.size)]
    np.testing.assert_allclose(curves.moving_average(x, w), loop)


def test_trials_to_90pct_on_known_curves():
    ramp = np.minimum(np.arange(1, 201) / 50.0, 1.0)  # reaches 1.0 at trial 50, final = 1.0
    t, reached = curves.trials_to_fraction(ramp)
    w = curves.smoothing_window(200)  # trailing window delays the crossing by about w / 2
    assert reached and 45 + w // 2 - 1 <= t <= 45 + w // 2 + 1
    assert curves.trials_to_fraction(np.zeros(10)) == (1, True)  # final 0: reached at once
    down = np.concatenate([np.full(50, 10.0), np.zeros(5), np.full(5, -1.0)])  # final < 0
    assert curves.trials_to_fraction(down)[0] == 1
    assert curves.final_count(500) == 50 and curves.smoothing_window(500) == 25


def test_nominal_seeds_extend_the_fixed_list():
    assert fig4_trial.nominal_seeds(5) == (0, 1, 2, 3, 4)
    assert fig4_trial.nominal_seeds(3) == (0, 1, 2)
    assert fig4_trial.nominal_seeds(7) == (0, 1, 2, 3, 4, 5, 6)


def test_no_plots_writes_everything_but_the_png(tmp_path):
    tiny = [*TINY[:2], "experiment.runs=1", "experiment.trials=2", *TINY[4:]]
    argv = ["experiment", "wargus-fig4", "--out", str(tmp_path), "--no-progress", "--no-plots"]
    assert main([*argv, *tiny]) == 0
    assert (tmp_path / "metrics.json").is_file() and (tmp_path / "per_trial.csv").is_file()
    assert not (tmp_path / "fig4.png").exists()


def test_taskvar_eval_runs_every_method_on_a_repetition_bundle(results, tmp_path, capsys):
    out = tmp_path / "eval"
    argv = ["eval", "--checkpoint", str(results / "rep0" / "final.pt"), "--method", "all"]
    assert (
        main(
            [*argv, "--test", "fast_patrol", "--episodes", "4", "--no-progress", "--out", str(out)]
        )
        == 0
    )
    printed = capsys.readouterr().out
    for method in ("averaging", "options", "interruption", "hierarchy"):
        assert method in printed
    m = json.loads((out / "metrics.json").read_text())
    assert m["methods"] == ["averaging", "options", "interruption", "hierarchy"]
    assert (
        m["test"] == "fast_patrol"
        and (out / "episodes.csv").is_file()
        and (out / "eval.png").is_file()
    )


# ---- relations a wrong implementation would break (issue 33, item 5) ---------------------------


def _trailing_mean(x: list[float], w: int) -> list[float]:
    return [
        sum(x[max(0, i - w + 1) : i + 1]) / len(x[max(0, i - w + 1) : i + 1]) for i in range(len(x))
    ]


def _recompute(rows: list[dict[str, str]]) -> dict[str, dict[str, float]]:
    """Each method's figures from ``per_trial.csv``'s rows, by plain loops (not fig4_metrics)."""
    out = {}
    for name in METHODS:
        mine = [r for r in rows if r["method"] == name]
        reps = sorted({int(r["rep"]) for r in mine})
        trials = sorted({int(r["trial"]) for r in mine})
        items = {(int(r["rep"]), int(r["trial"])): float(r["items"]) for r in mine}
        curve = [sum(items[rep, t] for rep in reps) / len(reps) for t in trials]
        n_final = max(1, math.ceil(0.1 * len(trials)))
        final = sum(curve[-n_final:]) / n_final
        smooth = _trailing_mean(curve, max(1, len(trials) // 20))
        t90 = next((i + 1 for i, v in enumerate(smooth) if v >= 0.9 * final), len(trials))
        per_rep = [sum(items[rep, t] for t in trials) / len(trials) for rep in reps]
        inter = [float(r["interruptions"]) for r in mine]
        out[name] = {
            "curve_mean": curve,
            "final_score": final,
            "trials_to_90pct": t90,
            "mean_over_trials": sum(per_rep) / len(per_rep),
            "interruptions_per_episode": sum(inter) / len(inter),
        }
    return out


@pytest.mark.parametrize(
    "csv_name, block", [("per_trial.csv", None), ("per_trial_heldout.csv", "heldout")]
)
def test_metrics_recomputed_from_the_csv_equal_metrics_json(results, csv_name, block):
    m = json.loads((results / "metrics.json").read_text())
    m = m if block is None else m[block]
    rows = list(csv.DictReader((results / csv_name).open()))
    assert len(rows) == REPS * TRIALS * len(METHODS)
    for name, want in _recompute(rows).items():
        got = m["methods"][name]
        assert got["curve_mean"] == pytest.approx(want["curve_mean"], rel=1e-12, abs=1e-12)
        assert got["final_score"] == pytest.approx(want["final_score"], rel=1e-12, abs=1e-12)
        assert got["trials_to_90pct"] == want["trials_to_90pct"]
        assert got["mean_over_trials"]["mean"] == pytest.approx(want["mean_over_trials"], abs=1e-12)
        assert got["interruptions_per_episode"] == pytest.approx(
            want["interruptions_per_episode"], abs=1e-12
        )


def test_held_out_test_phases_play_sealed_instances_paired_and_apart_from_nominal():
    from taskvar_torch.families import HELDOUT_SEEDS

    cfg = load_config(fig4.default_config_path(), TINY)
    k, trials = 5, len(HELDOUT_SEEDS) // 5
    env = fig4_agent.make_heldout_test_env(cfg, k, seed=0, first_trial=0, trials=trials)
    seeds = env.reset()["instance", "seed"].view(trials, len(METHODS), k)
    assert (seeds == seeds[:, :1]).all()  # every method plays the same instances (paired)
    assert sorted(seeds[:, 0].flatten().tolist()) == list(HELDOUT_SEEDS)  # each sealed one once
    nominal = fig4_agent.make_test_env(cfg, k, seed=0, trials=2).reset()["instance", "seed"]
    assert not set(nominal.tolist()) & set(HELDOUT_SEEDS)


def test_the_hierarchy_hands_fe_exactly_the_states_with_a_patrol_in_sight(results):
    """With the root never robust (tau huge), Algorithm 2's descent must give FE every state
    where a patrol is in sight and TG every other: the control split is that indicator."""
    from taskvar_torch.experiments.evaluation import run_episodes
    from taskvar_torch.factory import make_method_controller
    from taskvar_torch.families.wargus.dynamics import PATROL_SEEN
    from taskvar_torch.heads.robustness import RobustnessCalibration

    heads, cfg = load_heads(results / "rep0" / "final.pt")
    env = make_env(cfg, 24, seed=5, instances="train", validate_actions=False)
    subtasks = make_subtasks(cfg, env)
    O = len(heads.option_names)  # noqa: E741
    cal = RobustnessCalibration(torch.full((O,), 1e6), torch.ones(O))
    ctrl = make_method_controller(cfg, "hierarchy", heads, subtasks, calibration=cal)
    out = run_episodes(
        TransformedEnv(env, ctrl.primer()), ctrl, trace_keys=(keys.OPTION, PATROL_SEEN)
    )
    alive = out["trace", "alive"]
    option = out["trace", keys.OPTION][alive]
    seen = out["trace", PATROL_SEEN][alive].bool()
    fe, tg = heads.option_names.index("FE"), heads.option_names.index("TG")
    assert seen.any() and (~seen).any()  # both kinds of state occur
    assert torch.equal(option == fe, seen) and torch.equal(option == tg, ~seen)
    split = torch.bincount(option, minlength=O).double() / option.numel()
    assert float(split.sum()) == pytest.approx(1.0) and float(split[fe]) == pytest.approx(
        float(seen.double().mean())
    )
