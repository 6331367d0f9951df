"""The scale experiment's baselines (docs/scale.md#baselines, issue 31): with
``baselines=[recurrent, informed]`` every cell and seed trains them on its own config and frame
budget (``train_recurrent.train_baseline``, as ``taskvar train-baselines`` does) and plays them on
the cell's paired test episodes and held-out ones, as new ``methods`` entries; the paper methods'
numbers are bit for bit those of a run without baselines."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import pytest
import torch
from scale_runs import assert_same, record_episodes, run_scale, stack_episodes, without_timing

from taskvar_torch import contract as families
from taskvar_torch.config import METHODS
from taskvar_torch.families import FAMILIES
from taskvar_torch.heads.recurrent import BASELINES
from taskvar_torch.study import scale, scale_cell, scale_config, scale_report
from taskvar_torch.training.run_state import seed_config

torch.set_num_threads(1)

BASES = ["recurrent", "informed"]
CELL = "windy-5x5-n4"
HELD = 6  # held-out episodes per method (eval_episodes is 8)
TINY = [  # one tiny windy cell, two seeds, a few hundred frames, short episodes
    "num_envs=[4]",
    "seeds=2",
    "total_frames=200",
    "curve_points=0",
    "eval_episodes=8",
    "eval_batch_size=4",
    f"heldout_episodes={HELD}",
    "only=[windy-5x5]",
    "head_report=false",
    'overrides=["heads.hidden=[32]",train.batch_size=32,env.horizon=30]',
]
NEW_CELL_KEYS = {"baseline_training", "baseline_train_seconds", "baseline_eval_seconds"}


def _strip_baselines(x):
    """``x`` without every baseline entry and key this feature adds."""
    if isinstance(x, dict):
        drop = {*BASES, "baselines", *NEW_CELL_KEYS}
        return {k: _strip_baselines(v) for k, v in x.items() if k not in drop}
    if isinstance(x, list):
        return [_strip_baselines(v) for v in x]
    return x


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The tiny run with both baselines (every episode batch played and every baseline trained
    recorded) and the same run without them."""
    played = []  # (family, env seed, policy name, instance fields, start cells) per batch
    trained = []  # (config, method, folder) per train_baseline call
    train_baseline = scale_cell.train_baseline

    def spy(mp):
        def trains(cfg, method, out_dir, *args, **kwargs):
            trained.append((cfg, method, out_dir))
            return train_baseline(cfg, method, out_dir, *args, **kwargs)

        record_episodes(mp, played)
        mp.setattr(scale_cell, "train_baseline", trains)

    on = tmp_path_factory.mktemp("baselines-on")
    off = tmp_path_factory.mktemp("baselines-off")
    m_on = run_scale(on, *TINY, f"baselines=[{','.join(BASES)}]", spy=spy)
    m_off = run_scale(off, *TINY)
    return {"on": (on, m_on), "off": (off, m_off), "played": played, "trained": trained}


@pytest.mark.slow
def test_every_cell_and_seed_has_the_baseline_entries(runs):
    out, m = runs["on"]
    assert m["baselines"] == BASES and m["methods"] == list(METHODS)
    assert "baselines" in m["notes"]
    for c in m["cells"]:
        assert list(c["methods"]) == [*METHODS, *BASES]  # new entries after the methods'
        blocks = [
            (c["methods"], 8),
            *((run["methods"], 8) for run in c["per_seed"]),
            (c["heldout"]["methods"], HELD),
            *((run["methods"], HELD) for run in c["heldout"]["per_seed"]),
        ]
        for methods, episodes in blocks:
            for b in BASES:
                r = methods[b]
                assert r["episodes"] == episodes and r["ci95"] >= 0
                assert -30 <= r["mean_return"] <= -1  # windy: -1 a step, 30-step episodes
                assert set(r) == {"mean_return", "ci95", "mean_length", "episodes", "gap_closed"}
                assert r["gap_closed"] is not None  # windy has the exact averaging optimum
        for over in (c["over_seeds"], c["heldout"]["over_seeds"]):
            assert list(over) == [*METHODS, *BASES]
            for b in BASES:
                assert len(over[b]["returns"]) == 2 and over[b]["gap_closed"] is not None
        assert [(t["seed"], t["method"]) for t in c["baseline_training"]] == [
            (s, b) for s in c["seeds"] for b in BASES
        ]
        for t in c["baseline_training"]:  # each an agent of its own, trained apart
            assert t["frames"] >= 200 and t["updates"] > 0
            assert t["with_heads"] is False and t["train_seconds"] > 0
        assert c["baseline_train_seconds"] == pytest.approx(
            sum(t["train_seconds"] for t in c["baseline_training"])
        )
        assert c["baseline_eval_seconds"] > 0
    for b in BASES:  # keep_checkpoints=false: the baselines' bundles are removed once read
        assert not list(out.glob(f"cells/*/seed*/{b}.pt"))
    table = scale_report.format_table(m)
    heads = [x for x in table.splitlines() if x.startswith("case ")]
    assert len(heads) == 2 and all("recurrent" in h and "informed" in h for h in heads)
    seeds_lines = [x for x in table.splitlines() if "seeds 0-1:" in x]
    assert seeds_lines and all("recurrent" in x and "informed" in x for x in seeds_lines)
    assert "Held-out instances" in table  # its header is the second "case" line above
    off_table = scale_report.format_table(runs["off"][1])
    assert "recurrent" not in off_table and "informed" not in off_table
    with open(out / "scale.csv") as f:
        rows = list(csv.DictReader(f))
    assert {(r["seed"], r["method"]) for r in rows} == {
        (str(s), name) for s in (0, 1) for name in (*METHODS, *BASES)
    }


@pytest.mark.slow
def test_the_methods_numbers_are_bit_for_bit_those_of_a_run_without_baselines(runs):
    (on, m_on), (off, m_off) = runs["on"], runs["off"]
    assert set(m_on) - set(m_off) == {"baselines"}
    for c_on, c_off in zip(m_on["cells"], m_off["cells"]):
        assert set(c_on) - set(c_off) == NEW_CELL_KEYS
    assert without_timing(_strip_baselines(m_on)) == without_timing(m_off)
    with open(on / "scale.csv") as f:
        rows_on = [r for r in csv.DictReader(f) if r["method"] not in BASES]
    with open(off / "scale.csv") as f:
        rows_off = list(csv.DictReader(f))
    assert [without_timing(r) for r in rows_on] == [without_timing(r) for r in rows_off]
    for k in range(2):  # the trained heads too: every bit
        a = torch.load(on / "cells" / CELL / f"seed{k}" / "heads.pt", weights_only=False)
        b = torch.load(off / "cells" / CELL / f"seed{k}" / "heads.pt", weights_only=False)
        assert_same(a, b)


@pytest.mark.slow
def test_each_seed_trains_its_baselines_on_the_cells_config_and_budget(runs):
    out, m = runs["on"]
    cfg = scale.load_scale_config(scale.default_config_path(), TINY, quick=True)
    ccfg = scale_config.case_config(cfg, cfg.selected()[0], 4)
    trained = runs["trained"]
    # each baseline trains apart, seed by seed
    assert [(c.seed, meth) for c, meth, *_ in trained] == [(s, b) for s in (0, 1) for b in BASES]
    for bcfg, _, folder in trained:
        k = bcfg.seed - ccfg.seed
        assert bcfg == seed_config(ccfg, k)  # the cell's own config: the heads' settings
        assert bcfg.train.total_frames == 200
        root = Path(folder).parents[2]  # out, or its staging folder beside it (ResultsFolder)
        assert Path(folder) == root / "cells" / CELL / f"seed{k}"  # beside the seed's bundle
        assert root.resolve().parent == Path(out).resolve().parent


@pytest.mark.slow
def test_the_baselines_play_the_methods_paired_episodes(runs):
    played = runs["played"]
    nominal_seed = runs["on"][1]["test_seed"]
    held_seed = FAMILIES["windy"].tests["heldout"].seed
    for seed, episodes in ((nominal_seed, 8), (held_seed, HELD)):
        by_policy: dict[str, list] = {}
        for _, s, name, inst, start in played:
            if s == seed:
                by_policy.setdefault(name, []).append((inst, start))
        assert {"averaging", "options", "interruption", *BASES} <= set(by_policy)
        want = stack_episodes(by_policy["averaging"])
        for b in BASES:
            got = stack_episodes(by_policy[b])
            assert len(got[0]) == 2 * episodes  # two seeds' controllers, the same episodes
            for a, w in zip(got, want):
                assert torch.equal(a, w), b


def test_the_baseline_phase_leaves_the_global_random_streams_alone(tmp_path):
    """Training and scoring the baselines draws no number from the streams the methods' evaluation
    (or the next cell) uses: torch's, NumPy's and Python's states are as they were."""
    import random

    import numpy as np

    extra = ["seeds=1", "baselines=[recurrent,informed]", "heldout_episodes=0"]
    cfg = scale.load_scale_config(scale.default_config_path(), [*TINY, *extra], quick=True)
    ccfg = scale_config.case_config(cfg, cfg.selected()[0], 4)
    ecfg = seed_config(ccfg, 0)
    states = lambda: (torch.get_rng_state(), np.random.get_state()[1].copy(), random.getstate())  # noqa: E731
    torch.manual_seed(3), np.random.seed(3), random.seed(3)
    before = states()
    cell, methods = {}, {}
    ctrls = scale_cell.baseline_phase(cfg, ccfg, ecfg, [tmp_path], cell, [methods], -30.0, -5.0)
    after = states()
    assert torch.equal(before[0], after[0]) and (before[1] == after[1]).all()
    assert before[2] == after[2]
    assert list(ctrls[0]) == list(methods) == BASES and len(cell["baseline_training"]) == 2


@pytest.mark.parametrize("value", ["[x]", "[recurrent,recurrent]", "[averaging]"])
def test_a_bad_baseline_name_is_a_one_line_error(value):
    with pytest.raises(ValueError, match="baselines") as e:
        scale.load_scale_config(scale.default_config_path(), [f"baselines={value}"])
    msg = str(e.value)
    assert "\n" not in msg and all(b in msg for b in BASELINES)


def test_informed_without_features_is_a_one_line_error_before_any_training(tmp_path, monkeypatch):
    path = scale.default_config_path()
    assert scale.load_scale_config(path, ["only=[wargus-32x32]", "baselines=[informed]"])
    fam = families.family  # below: a Wargus without features (every built-in family has some)
    monkeypatch.setattr(
        families, "family", lambda c: dataclasses.replace(fam(c), informed_features=None)
    )
    with pytest.raises(ValueError, match="family 'wargus'") as e:
        scale.load_scale_config(path, ["only=[windy-5x5,wargus-32x32]", "baselines=[informed]"])
    assert "\n" not in str(e.value) and "['recurrent', 'blind']" in str(e.value)
    cfg = scale.load_scale_config(path, ["only=[windy-5x5,wargus-32x32]"])
    cfg = dataclasses.replace(cfg, baselines=("recurrent", "informed"))  # past the loader

    def no_training(*args, **kwargs):
        raise AssertionError("a cell trained before the baselines were checked")

    monkeypatch.setattr(scale_cell, "train", no_training)
    with pytest.raises(ValueError, match="family 'wargus'") as e:
        scale.scale(cfg, tmp_path / "out", progress=False, plots=False)
    assert "\n" not in str(e.value) and "['recurrent', 'blind']" in str(e.value)
    assert scale.load_scale_config(path, ["only=[wargus-32x32]", "baselines=[recurrent]"])


def test_no_baselines_by_default():
    assert scale.load_scale_config(scale.default_config_path()).baselines == ()
    field = {f.name: f for f in dataclasses.fields(scale_config.ScaleConfig)}["baselines"]
    assert field.default == ()
