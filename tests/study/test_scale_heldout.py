"""The scale experiment's held-out block (docs/scale.md#held-out-instances, issue 33): every cell
(and every seed) also plays each method on the family's sealed held-out test distribution
(``Family.tests["heldout"]``), paired across methods, under the new keys ``heldout``; the nominal
numbers are bit for bit those of a run with the held-out block off (``heldout_episodes=0``)."""

from __future__ import annotations

import pytest
import torch
from scale_runs import (
    TIMING,
    assert_same,
    record_episodes,
    run_scale,
    stack_episodes,
    without_timing,
)

from taskvar_torch.config import METHODS
from taskvar_torch.families import FAMILIES, HELDOUT_SEED, HELDOUT_SIZE
from taskvar_torch.study import scale, scale_cell, scale_config, scale_eval, scale_report

torch.set_num_threads(1)

EPISODES = 6  # held-out episodes per method (eval_episodes is 8: the key is honoured)
TINY = [  # two tiny cases (windy 5x5, Wargus 12x12 with 40-step episodes), two seeds, one N
    "num_envs=[4]",
    "seeds=2",
    "total_frames=200",
    "curve_points=0",
    "eval_episodes=8",
    "eval_batch_size=4",
    "only=[windy-5x5,wargus-32x32]",
    "head_report=false",
    'overrides=[env.wargus.size=12,env.wargus.horizon=40,"heads.hidden=[32]",train.batch_size=32]',
]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The tiny run with the held-out block (every test env and episode it played recorded) and
    the same run with it off."""
    played = []  # (family, env seed, policy name, instance fields, start cells) per batch
    on = tmp_path_factory.mktemp("heldout-on")
    off = tmp_path_factory.mktemp("heldout-off")
    m_on = run_scale(
        on, *TINY, f"heldout_episodes={EPISODES}", spy=lambda mp: record_episodes(mp, played)
    )
    m_off = run_scale(off, *TINY, "heldout_episodes=0")
    return {"on": (on, m_on), "off": (off, m_off), "played": played}


@pytest.mark.slow
def test_every_cell_and_seed_has_a_heldout_block_for_every_method(runs):
    _, m = runs["on"]
    assert m["heldout"]["test"] == scale_eval.HELDOUT_TEST and m["heldout"]["episodes"] == EPISODES
    for c in m["cells"]:
        fam = FAMILIES[c["family"]]
        ref = m["heldout"]["references"][c["case"]]
        assert ref["seed"] == fam.tests["heldout"].seed == HELDOUT_SEED
        assert ref["random"]["episodes"] == EPISODES
        assert (ref["oracle_averaging"] is None) == (fam.averaging_optimum is None)
        h = c["heldout"]
        blocks = [h["methods"], *(run["methods"] for run in h["per_seed"])]
        assert h["per_seed"][0]["methods"] == h["methods"]
        assert [run["seed"] for run in h["per_seed"]] == c["seeds"]
        for methods in blocks:  # the nominal block's shape: the same methods, n/a alike
            assert list(methods) == list(c["methods"]) == list(METHODS)
            for name, r in methods.items():
                assert (r is None) == (c["methods"][name] is None), name
                if r is not None:
                    assert r["episodes"] == EPISODES
                    assert set(r) == set(c["methods"][name])
        assert set(h["over_seeds"]) == set(c["over_seeds"])
    table = scale_report.format_table(m)
    assert "Held-out instances" in table
    assert "Held-out instances" not in scale_report.format_table(runs["off"][1])


@pytest.mark.slow
def test_the_nominal_results_are_bit_for_bit_those_of_a_run_without_it(runs):
    (on, m_on), (off, m_off) = runs["on"], runs["off"]
    assert set(m_on) - set(m_off) == {"heldout"} and set(m_off) <= set(m_on)
    for c_on, c_off in zip(m_on["cells"], m_off["cells"]):
        assert set(c_on) - set(c_off) == {"heldout"} and set(c_off) <= set(c_on)
    strip = {k: v for k, v in m_on.items() if k != "heldout"}
    strip["cells"] = [{k: v for k, v in c.items() if k != "heldout"} for c in m_on["cells"]]
    assert without_timing(strip) == without_timing(m_off)
    assert (on / "scale.csv").read_text() != "" and (
        _csvwithout_timing(on) == _csvwithout_timing(off)
    )
    for cell in ("windy-5x5-n4", "wargus-32x32-n4"):  # the trained heads too: every bit
        for k in range(2):
            a = torch.load(on / "cells" / cell / f"seed{k}" / "heads.pt", weights_only=False)
            b = torch.load(off / "cells" / cell / f"seed{k}" / "heads.pt", weights_only=False)
            assert_same(a, b)


def _csvwithout_timing(out):
    lines = (out / "scale.csv").read_text().splitlines()
    head = lines[0].split(",")
    keep = [i for i, k in enumerate(head) if k not in TIMING]
    return [[row.split(",")[i] for i in keep] for row in lines]


@pytest.mark.slow
def test_the_heldout_episodes_are_the_sealed_ones_paired_across_methods(runs):
    played = runs["played"]
    for fam_name in ("windy", "wargus"):
        dist = FAMILIES[fam_name].tests["heldout"]
        held = [p for p in played if p[0] == fam_name and p[1] == dist.seed]
        nominal = [p for p in played if p[0] == fam_name and p[1] != dist.seed]
        assert held and nominal
        assert all(p[1] < HELDOUT_SEED for p in nominal)  # the nominal test never plays the range
        by_policy: dict[str, list] = {}
        for _, _, name, inst, start in held:
            by_policy.setdefault(name, []).append((inst, start))
        # the references (random, oracle) and the methods: two seeds x the methods per cell
        assert {"RandomPolicy", "averaging", "options", "interruption"} <= set(by_policy)
        first = stack_episodes(next(iter(by_policy.values())))
        for name, batches in by_policy.items():
            eps = stack_episodes(batches)
            assert len(eps[0]) % EPISODES == 0, name
            for a, b in zip(eps, first):  # paired: every policy plays the same episodes
                n = min(len(a), len(b))
                assert torch.equal(a[:n], b[:n]), name
        if fam_name == "wargus":  # the distribution's own instance seeds, in order, sealed range
            sealed = dist.instances["seeds"]
            want = torch.tensor([sealed[i % len(sealed)] for i in range(EPISODES)])
            for name, batches in by_policy.items():
                seeds = torch.cat([inst["seed"] for inst, _ in batches]).reshape(-1, EPISODES)
                assert (seeds == want).all(), name
                assert ((seeds >= HELDOUT_SEED) & (seeds < HELDOUT_SEED + HELDOUT_SIZE)).all()
        else:  # windy: the training winds under the sealed seed, not the nominal episodes
            nominal_eps = stack_episodes([(inst, start) for *_, inst, start in nominal])
            assert not torch.equal(first[0][:EPISODES], nominal_eps[0][:EPISODES])


def test_heldout_references_leave_the_nominal_random_streams_alone():
    cfg = scale.load_scale_config(
        scale.default_config_path(), ["only=[windy-5x5]", "heldout_episodes=4"]
    )
    ccfg = scale_config.case_config(cfg, cfg.selected()[0], 4)
    torch.manual_seed(3)
    want = torch.rand(5)
    torch.manual_seed(3)
    refs = scale_cell.heldout_references(cfg, ccfg)
    assert torch.equal(torch.rand(5), want)
    assert refs["seed"] == FAMILIES["windy"].tests["heldout"].seed and refs["episodes"] == 4
    assert refs["oracle_averaging"]["mean_return"] >= refs["random"]["mean_return"]


@pytest.mark.parametrize("value", ["-1", "1.5", "true", "x"])
def test_bad_heldout_episodes_are_one_line_errors(value):
    with pytest.raises(ValueError, match="heldout_episodes") as e:
        scale.load_scale_config(scale.default_config_path(), [f"heldout_episodes={value}"])
    assert "\n" not in str(e.value)


def test_heldout_episodes_default_to_eval_episodes_and_zero_turns_it_off():
    path = scale.default_config_path()
    assert (
        scale.load_scale_config(path, ["only=[windy-5x5]", "eval_episodes=7"]).heldout_count() == 7
    )
    assert (
        scale.load_scale_config(path, ["only=[windy-5x5]", "heldout_episodes=0"]).heldout_count()
        == 0
    )
    assert (
        scale.load_scale_config(path, ["only=[windy-5x5]", "heldout_episodes=3"]).heldout_count()
        == 3
    )
