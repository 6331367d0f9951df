"""The memory estimate (taskvar_torch/config/memory.py): it never refuses a shipped config, it
refuses the absurd in one line naming the key, and it is conservative against what a run really
allocates (replay rows, networks, the windy observation table)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.config.memory import (
    FLOAT,
    HEADS,
    PARAM_COPIES,
    ROW_EXTRA,
    available_memory,
    check_memory,
    estimate,
    observation_size,
)
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.env import OBS_ENCODINGS, observation_table
from taskvar_torch.families.windy.env import observation_size as windy_observation_size
from taskvar_torch.training.replay import raw_transitions
from taskvar_torch.training.run_setup import build_run

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p for p in (ROOT / "configs").glob("*.yaml") if p.name != "scale.yaml")
GIB = 1 << 30


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_no_shipped_config_is_refused(path):
    """Every config in configs/ fits a 16 GiB machine by the estimate (the largest: ~2 GB)."""
    cfg = load_config(path)
    terms = estimate(cfg)
    assert sum(terms.values()) < 4 * GIB, terms
    check_memory(terms, available=16 * GIB)
    check_memory(estimate(cfg, training=False, episodes=cfg.eval.episodes), available=16 * GIB)


@pytest.mark.parametrize(
    "override, key",
    [
        (["env.num_envs=1000000000"], "env.num_envs"),
        (["train.buffer_size=1000000000000"], "train.buffer_size"),
        (["heads.hidden=[100000,100000]"], "heads.hidden"),
        (["train.batch_size=100000000", "train.buffer_size=100000000"], "train.batch_size"),
        pytest.param(  # builds the 1000x1000 layout: ~5 s
            ["env.windy.layout=generated", "env.windy.height=1000", "env.windy.width=1000"],
            "env.windy",
            marks=pytest.mark.slow,
        ),
    ],
)
def test_the_absurd_is_refused_naming_the_key_and_the_estimate(override, key):
    cfg = load_config(ROOT / "configs" / "windy_corridor.yaml", override)
    with pytest.raises(ValueError) as e:
        check_memory(estimate(cfg), available=64 * GIB)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{key} asks for too much memory")
    assert "68.7 GB is available here" in msg and f"lower {key}" in msg and "TB" in msg


def test_episode_rows_are_counted_under_the_flag_that_asks_for_them():
    cfg = load_config(ROOT / "configs" / "windy.yaml")
    with pytest.raises(ValueError, match=r"^--episodes asks for too much memory"):
        check_memory(estimate(cfg, training=False, episodes=10**12), available=64 * GIB)
    terms = estimate(cfg, training=False, episodes=10, episodes_key="experiment.episodes_per_run")
    assert "experiment.episodes_per_run" in terms and "train.buffer_size" not in terms


@pytest.mark.parametrize(
    "files, want",
    [
        ({"meminfo": "MemTotal: 16000 kB\nMemAvailable: 8000 kB\n"}, 8000 * 1024),
        (  # a cgroup limit below MemAvailable: its free part
            {
                "meminfo": "MemAvailable: 8000 kB\n",
                "memory.max": "4096000",
                "memory.current": "1000",
            },
            4096000 - 1000,
        ),
        (
            {"meminfo": "MemAvailable: 8000 kB\n", "memory.max": "max", "memory.current": "5"},
            8192000,
        ),
    ],
    ids=["meminfo", "cgroup-lower", "cgroup-unlimited"],
)
def test_the_available_memory_is_memavailable_or_the_cgroups_free_limit(files, want, monkeypatch):
    """Read from /proc/meminfo and the cgroup v2 files (here fakes of them, by file name)."""
    from taskvar_torch.config import memory

    def read_text(path, *args, **kwargs):
        if path.name not in files:
            raise FileNotFoundError(path)
        return files[path.name]

    monkeypatch.setattr(memory.Path, "read_text", read_text)
    assert available_memory() == want


def test_the_available_memory_here_is_at_most_memavailable():
    meminfo = Path("/proc/meminfo")
    if not meminfo.is_file():
        pytest.skip("no /proc/meminfo")
    fields = {
        ln.split(":")[0]: int(ln.split()[1]) * 1024 for ln in meminfo.read_text().splitlines()
    }
    available = available_memory()
    assert 0 < available <= 1.05 * fields["MemAvailable"] and available <= fields["MemTotal"]


@pytest.mark.parametrize(
    "config, overrides",
    [
        ("windy.yaml", []),
        ("windy_xl.yaml", ["env.num_envs=8"]),
        ("wargus.yaml", ["train.compile=false"]),
        ("taxi.yaml", []),
    ],
)
def test_the_estimate_bounds_what_a_run_allocates(config, overrides, tmp_path):
    """Replay rows as the run stores them, and every network's weights with their gradients,
    Adam moments and targets: no more than the estimate counts for them."""
    cfg = load_config(ROOT / "configs" / config, ["env.num_envs=4", *overrides])
    run = build_run(cfg, tmp_path, None)
    D = int(run.env.observation_spec[keys.OBSERVATION].shape[-1])
    assert observation_size(cfg) == D
    batch = run.env.rollout(3, policy=run.behaviour, break_when_any_done=False)
    rows = raw_transitions(batch, keep_instance=True)
    per_row = sum(v.element_size() * v.numel() for v in rows.values(True, True)) / rows.numel()
    assert per_row <= 2 * D * FLOAT + ROW_EXTRA
    terms = estimate(cfg)
    assert terms["train.buffer_size"] >= cfg.train.buffer_size * per_row
    learner = run.learner
    params = sum(p.numel() for p in learner.heads.parameters())
    targets = sum(p.numel() for p in learner.loss.target_heads.parameters())
    held = (params * 4 + targets) * FLOAT  # weights, gradients, two Adam moments; targets
    assert held <= terms["heads.hidden"]
    assert len(learner.heads.heads) <= HEADS and PARAM_COPIES >= 5


@pytest.mark.parametrize("encoding", OBS_ENCODINGS)
@pytest.mark.parametrize("radius", [0, 2])
def test_windy_observation_size_is_its_tables_width(encoding, radius):
    """The windy family's ``observation_size`` (the estimate's, without building the table)."""
    for layout in (windy.WindyLayout.named("default"), windy.make_layout(13, 17, num_exits=3)):
        table = observation_table(layout, encoding, radius)
        assert windy_observation_size(layout, encoding, radius) == table.shape[1]
