"""What ``make demo`` says about its numbers (issue 48): ``taskvar eval --explain`` reads the
table in words derived from its numbers (experiments/explain.py ``explain_table``), and the
training summary labels what the budget has not learnt (``families/windy/family.py`` ``_windy_summary``)."""

from __future__ import annotations

import copy

import pytest
import torch

from taskvar_torch.cli import main
from taskvar_torch.config import load_config
from taskvar_torch.experiments.explain import explain_table
from taskvar_torch.factory import load_heads
from taskvar_torch.families.windy import family as windy_family
from taskvar_torch.heads.validate import compare_with_oracle
from taskvar_torch.training import train

torch.set_num_threads(1)


def _method(ret, ci, exact=None, regret=None, rci=0.0, **extra):
    r = {"mean_return": ret, "mean_return_ci95": ci, "mean_length": -ret, **extra}
    if exact is not None:
        r["exact_mean_return"] = exact
    if regret is not None:
        r.update(regret_mean=regret, regret_ci95=rci)
    return r


def corridor_like() -> dict:
    """The demo's table: three paper methods alike, memory far better, the ceiling at the optimum."""
    options = dict(interruptions_per_episode=0.0, control={"exit_north": 0.0, "exit_south": 1.0})
    return {
        "episodes": 2000,
        "figures": ["eval.png", "regret.png"],
        "points": [
            {
                "shift": "",
                "methods": {
                    "averaging": _method(-3.655, 0.373, -3.72, 2.211, 0.312),
                    "options": _method(-3.655, 0.373, -3.72, 2.211, 0.312, **options),
                    "interruption": _method(-3.655, 0.373, -3.72, 2.211, 0.312, **options),
                    "recurrent": _method(-1.825, 0.024, None, 0.317, 0.024, regret_sampled=True),
                    "informed": _method(-1.508, 0.022, None, -0.0004, 0.018, regret_sampled=True),
                },
            }
        ],
    }


def test_the_demo_table_is_explained_from_its_numbers():
    text = explain_table(corridor_like())
    flat = " ".join(text.split())
    assert "regret: the exact per-instance optimum" in flat
    assert "from the sampled return for informed, recurrent" in flat
    assert "averaging, options, interruption: the same mean return, exact value and regret" in flat
    assert "interruption never fired" in flat and "ran exit_south on every step" in flat
    assert "recurrent (memory" in flat and "is better than every memoryless method" in flat
    assert "(best: averaging, 2.211 +-0.312)" in flat
    assert "informed (it sees the hidden instance; a ceiling here): at the exact optimum" in flat
    assert "averaging, options, interruption draw on top of each other" in flat
    assert "docs/memory.md" in flat and "docs/evaluation.md" in flat
    assert max(len(line) for line in text.splitlines()) <= 100


def test_memory_is_said_to_win_only_where_the_cis_are_apart():
    m = corridor_like()
    ms = m["points"][0]["methods"]
    ms["recurrent"].update(regret_mean=1.9, regret_ci95=0.2)  # overlaps averaging's 2.211 +-0.312
    flat = " ".join(explain_table(m).split())
    assert "ties with the best memoryless method within their 95% CIs" in flat
    assert "better than every" not in flat
    ms["recurrent"].update(regret_mean=3.5, regret_ci95=0.2)
    flat = " ".join(explain_table(m).split())
    assert "is worse than the best memoryless method, 95% CIs apart" in flat
    ms["informed"].update(regret_mean=0.4, regret_ci95=0.1)
    assert "regret 0.400 +-0.100: short of the exact optimum" in " ".join(explain_table(m).split())


def test_informed_below_a_memoryless_method_is_said_to_be_no_ceiling_and_blind_is_the_control():
    m = corridor_like()
    ms = m["points"][0]["methods"]
    ms["blind"] = _method(-3.0, 0.1, None, 1.5, 0.1, regret_sampled=True)
    ms["informed"].update(regret_mean=2.0, regret_ci95=0.1)  # behind blind, CIs apart
    flat = " ".join(explain_table(m).split())
    assert "informed (it sees the hidden instance; no ceiling here: it is behind blind" in flat
    assert "recurrent is ahead of blind, 95% CIs apart: memory, not its own stream, pays" in flat
    assert "(best: blind, 1.500 +-0.100)" in flat  # blind is memoryless: it can be the best one
    ms["recurrent"].update(regret_mean=1.45, regret_ci95=0.1)
    flat = " ".join(explain_table(m).split())
    assert "recurrent ties with blind within their 95% CIs: no gain from memory shown here" in flat


def test_methods_that_differ_are_not_called_alike_and_ties_need_overlapping_cis():
    m = corridor_like()
    ms = m["points"][0]["methods"]
    ms["options"].update(mean_return=-3.7, exact_mean_return=-3.75, regret_mean=2.3)
    ms["interruption"].update(
        mean_return=-5.0, exact_mean_return=-5.1, regret_mean=3.6, interruptions_per_episode=0.4
    )
    flat = " ".join(explain_table(m).split())
    assert "acted alike" not in flat and "draw on top" not in flat
    assert "options (regret 2.300 +-0.312) ties with averaging (2.211 +-0.312) within" in flat
    assert (
        "interruption (regret 3.600 +-0.312) is behind averaging (2.211 +-0.312), 95% CIs" in flat
    )


def test_without_an_optimum_the_best_is_the_highest_return():
    m = {
        "episodes": 100,
        "points": [
            {
                "shift": "",
                "methods": {
                    "averaging": _method(2.6, 0.1),
                    "hierarchy": _method(2.0, 0.1, interruptions_per_episode=3.0, control={}),
                    "recurrent": _method(3.2, 0.1),
                },
            }
        ],
    }
    flat = " ".join(explain_table(m).split())
    assert "regret" not in flat and "exact:" not in flat
    assert "hierarchy (mean return 2.000 +-0.100) is behind averaging (2.600 +-0.100)" in flat
    assert "is better than every memoryless method, 95% CIs apart (best: averaging" in flat


def test_without_an_oracle_only_what_was_measured_and_a_zero_wide_ci_is_explained():
    """A family with no exact oracle (the Gymnasium adapter): alike methods share a mean return,
    never an 'exact value'; a CI that is 0 wide (every episode ran to the cap) is named where a
    separation rests on it; interruption's firing is said either way (issue 59)."""
    stay = dict(interruptions_per_episode=0.0, control={"upright": 1.0, "centre": 0.0})
    m = {
        "episodes": 100,
        "points": [
            {
                "shift": "",
                "methods": {
                    "averaging": _method(50.0, 3.1),
                    "options": _method(1000.0, 0.0, **stay),
                    "interruption": _method(1000.0, 0.0, **stay),
                },
            }
        ],
    }
    m["points"][0]["methods"]["options"]["mean_length"] = 1000.0
    flat = " ".join(explain_table(m).split())
    assert "options, interruption: the same mean return (1000.000 +-0.000)" in flat
    assert "exact value" not in flat
    assert "interruption never fired" in flat
    assert "averaging (mean return 50.000 +-3.100) is behind options" in flat
    assert (
        "the 95% CI of options is 0 wide: every one of its episodes scored the same, 1000" in flat
    )
    ms = m["points"][0]["methods"]
    ms["interruption"].update(
        mean_return=990.0, mean_return_ci95=5.0, interruptions_per_episode=0.0
    )
    flat = " ".join(explain_table(m).split())
    assert "interruption never fired on these episodes (0 interruptions per episode)" in flat
    ms["interruption"]["interruptions_per_episode"] = 2.5
    flat = " ".join(explain_table(m).split())
    assert "interruption cut a running option short 2.50 times per episode" in flat


def test_a_shift_curve_gets_the_columns_only():
    m = corridor_like()
    m["points"].append(copy.deepcopy(m["points"][0]))
    text = explain_table(m)
    assert "How to read the table:" in text and "What it shows:" not in text


def test_the_training_summary_names_an_option_the_budget_has_not_learnt(monkeypatch):
    cfg = load_config("configs/windy.yaml", ["train.total_frames=1234"])
    from taskvar_torch.families.windy import WindyOracle

    heads = WindyOracle("default").heads()
    report = {
        "averaging_return": -5.0,
        "oracle_averaging_return": -5.0,
        "option_returns": [-100.0, -5.0],
        "oracle_option_returns": [-4.0, -5.0],
        "mu_bar_agreement": 1.0,
        "mu_bar_cells": 2,
        "max_value_error": 26.9,
        "max_value_error_per_option": [26.9, 0.97],
        "interruption_agreement": 0.8,
        "interruption_pairs": 6,
    }
    import taskvar_torch.heads.validate as validate

    monkeypatch.setattr(validate, "compare_with_oracle", lambda h, o: report)
    lines = windy_family._windy_summary(heads, cfg)
    north, south = (line for line in lines if line.startswith("  option"))
    assert "not learnt: never reaches its exit in 100 steps" in north
    assert "not learnt" not in south
    assert "per option: exit_north 26.900, exit_south 0.970" in "\n".join(lines)
    assert (
        lines[-1] == "  undertrained at 1234 training frames: option(s) exit_north not learnt yet"
    )
    report["option_returns"] = [-4.0, -5.0]  # every option learnt: no label
    assert "not learnt" not in "\n".join(windy_family._windy_summary(heads, cfg))


@pytest.mark.slow
def test_taskvar_eval_explain_and_the_summary_on_a_trained_bundle(tmp_path, capsys):
    tiny = [
        "env.num_envs=4",
        "train.frames_per_batch=100",
        "train.total_frames=300",
        "train.checkpoint_every=0",
        "train.init_random_frames=100",
        "train.batch_size=16",
        "train.updates_per_batch=1",
        "train.buffer_size=1000",
    ]
    train(load_config("configs/windy.yaml", tiny), tmp_path / "run", progress=False)
    args = ["eval", "--checkpoint", str(tmp_path / "run" / "final.pt"), "--method", "all"]
    assert main([*args, "--episodes", "20", "--no-progress", "--explain"]) == 0
    out = capsys.readouterr().out
    table, explanation = out.split("How to read the table:")
    assert "regret" in table and "What it shows:" in explanation
    assert main([*args, "--episodes", "20", "--no-progress"]) == 0
    assert "How to read the table" not in capsys.readouterr().out  # only when asked
    heads, cfg = load_heads(tmp_path / "run" / "final.pt")
    r = compare_with_oracle(heads, windy_family._windy_oracle(cfg))
    assert max(r["max_value_error_per_option"]) == pytest.approx(r["max_value_error"])
    summary = "\n".join(windy_family._windy_summary(heads, cfg))
    assert "per option: exit_north " in summary and "exit_south " in summary
