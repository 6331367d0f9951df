"""The recurrent baseline's curve in the Figure 4 protocol (families/wargus/fig4_recurrent.py)."""

from __future__ import annotations

import csv
import json

import pytest
import torch

from taskvar_torch.config import load_config
from taskvar_torch.families.wargus import fig4, fig4_repetition
from taskvar_torch.families.wargus import fig4_recurrent as rec
from taskvar_torch.heads.recurrent import load_baseline

torch.set_num_threads(1)

TINY = [
    "env.wargus.size=16",
    "env.wargus.horizon=50",
    "experiment.runs=2",
    "experiment.trials=3",
    "experiment.learning_episodes_per_trial=6",
    "experiment.test_episodes_per_trial=3",
    "train.init_random_frames=50",
    "train.batch_size=32",
    "train.frames_per_batch=64",
    "train.buffer_size=5000",
    "heads.hidden=[32]",
    "train.compile=false",  # configs/wargus.yaml compiles; a test run does not pay it off
]


def test_learning_phase_stores_whole_episodes_and_takes_the_due_updates():
    """The replay holds every live step once, each episode ending at its done; the agent takes
    ``updates_per_batch`` steps per ``frames_per_batch`` frames played past the random frames."""
    cfg = load_config(fig4.default_config_path(), TINY)
    torch.manual_seed(0)
    agent = rec.make_recurrent_agent(cfg, seed=0)
    frames = 0
    for _ in range(3):
        learned = rec.learning_phase(agent)
        frames += learned["frames"]
    t = cfg.train
    assert len(agent.learner.buffer) == frames == agent.frames
    stored = agent.learner.buffer[:]
    done = stored.get(("next", "done")).reshape(-1)
    assert int(done.sum()) == 3 * cfg.experiment.learning_episodes_per_trial
    assert bool(done[-1])  # the last stored step ends an episode
    assert int(stored.get("is_init").sum()) == int(done.sum())  # one start per episode
    boundaries = range(t.frames_per_batch, frames + 1, t.frames_per_batch)
    due = sum(agent.learner.updates_per_batch for b in boundaries if b >= t.init_random_frames)
    assert agent.updates == due > 0
    # its slices are trajectories: each step's observation is the step before's next one
    for _ in range(10):
        s = agent.learner.buffer.sample()
        inner = ~s["is_init"].reshape(-1)[1:]  # consecutive rows of one slice
        nxt, now = s["next", "observation"][:-1][inner], s["observation"][1:][inner]
        assert inner.any() and torch.equal(now, nxt)
        assert not bool(s["next", "done"].reshape(-1)[:-1][inner].any())
        # the state each step hands on is stored, and is the next step's (both loss passes
        # start a slice from stored states)
        handed, taken = s["next", "recurrent_state"][:-1][inner], s["recurrent_state"][1:][inner]
        assert torch.equal(handed, taken) and bool(handed.abs().sum() > 0)


@pytest.mark.slow
def test_recurrent_curve_beside_unchanged_paper_methods(tmp_path):
    """``experiment.baselines=[recurrent]`` adds its nominal and held-out curves, cost, CSV rows and
    ``rep{r}/recurrent.pt`` (loadable, played by ``taskvar eval``); the paper's methods give the
    same numbers and weights as without it."""
    plain = load_config(fig4.default_config_path(), TINY)
    with_rec = load_config(fig4.default_config_path(), [*TINY, "experiment.baselines=[recurrent]"])
    a = fig4.wargus_fig4(plain, tmp_path / "plain", progress=False, plots=False)
    b = fig4.wargus_fig4(with_rec, tmp_path / "rec", progress=False, plots=True)
    for name, m in a["methods"].items():
        assert b["methods"][name]["curve_per_rep"] == m["curve_per_rep"], name
        held = b["heldout"]["methods"][name]["curve_per_rep"]
        assert held == a["heldout"]["methods"][name]["curve_per_rep"], name
    for r in range(2):
        x = torch.load(tmp_path / f"plain/rep{r}/final.pt", weights_only=True)["models"]["heads"]
        y = torch.load(tmp_path / f"rec/rep{r}/final.pt", weights_only=True)["models"]["heads"]
        assert all(torch.equal(v, y[k]) for k, v in x.items())
    R, T = 2, 3
    curve = b["methods"]["recurrent"]["curve_per_rep"]
    assert len(curve) == R and all(len(c) == T for c in curve)
    assert "mean_first_half" in b["heldout"]["methods"]["recurrent"]
    cost = b["timing"]["baselines"]["recurrent"]
    assert set(cost["cpu_seconds_per_trial"]) == set(rec.PHASES)
    assert all(f > 0 for f in cost["frames_per_repetition"])
    with open(tmp_path / "rec" / fig4_repetition.BASELINES_CSV) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == R * T and {r["method"] for r in rows} == {"recurrent"}
    assert float(rows[0]["items"]) == curve[0][0]
    assert json.loads((tmp_path / "rec/metrics.json").read_text())["methods"].keys() >= {
        "hierarchy",
        "recurrent",
    }
    assert (tmp_path / "rec/fig4.png").stat().st_size > 0
    ctrl, cfg = load_baseline(tmp_path / "rec/rep1/recurrent.pt")
    assert ctrl.name == "recurrent" and cfg.seed == 1  # the repetition's seed


def test_fig4_baselines_are_checked():
    with pytest.raises(ValueError, match=r"experiment.baselines must be .*\['recurrent'\]"):
        load_config(fig4.default_config_path(), [*TINY, "experiment.baselines=[informed]"])
