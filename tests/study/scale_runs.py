"""What the scale experiment's tests share (tests/study/test_scale_*.py): a tiny run through the
command line, a spy recording every batch of test episodes played, and comparisons that leave the
measured times out."""

from __future__ import annotations

import json

import pytest
import torch

from taskvar_torch import keys
from taskvar_torch.cli import main
from taskvar_torch.experiments import paired
from taskvar_torch.study import scale_cell

TIMING = {  # measured times and memory: not reproducible, so not compared
    "wall_seconds", "train_seconds", "eval_seconds", "frames_per_second", "peak_rss_mb",
    "frames_per_second_all_seeds", "seconds",
}  # fmt: skip


def run_scale(out, *overrides, spy=None) -> dict:
    """``taskvar experiment scale --quick`` into ``out`` with ``overrides`` (200 bootstrap
    replications per CI: the test's time); ``spy(mp)`` may patch more for the run. Its
    ``metrics.json``."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(scale_cell, "SEED_CI_REPS", 200)
        if spy is not None:
            spy(mp)
        argv = ["experiment", "scale", "--quick", "--out", str(out), "--no-progress", "--no-plots"]
        assert main([*argv, *overrides]) == 0
    return json.loads((out / "metrics.json").read_text())


def record_episodes(mp: pytest.MonkeyPatch, played: list) -> None:
    """Patch the episode player (``experiments.paired.play``, which the scale evaluation plays
    through) so that every batch of episodes it plays is appended to ``played`` as ``(family, env
    seed, policy name, instance fields, start cells)`` (start cells zero where the family has
    none: Wargus)."""
    make_env, run_episodes = paired.make_env, paired.run_episodes
    envs = {}

    def made(cfg, *args, **kwargs):
        env = make_env(cfg, *args, **kwargs)
        envs[id(env)] = (cfg.family, kwargs["seed"])
        return env

    def ran(env, policy, *args, **kwargs):
        out = run_episodes(env, policy, *args, **kwargs)
        fam, seed = envs[id(getattr(env, "base_env", env))]
        name = getattr(policy, "name", type(policy).__name__)
        start = out.get("start", torch.zeros(out.batch_size, dtype=torch.int64))
        played.append((fam, seed, name, out[keys.INSTANCE].clone(), start.clone()))
        return out

    mp.setattr(paired, "make_env", made)
    mp.setattr(paired, "run_episodes", ran)


def stack_episodes(batches) -> tuple[torch.Tensor, torch.Tensor]:
    """(instance fields stacked per episode, start cells) of a list of ``(instance, start)``."""
    flat = [
        torch.cat([v.reshape(len(v), -1).double() for _, v in sorted(i.items())], -1)
        for i, _ in batches
    ]
    return torch.cat(flat), torch.cat([s for _, s in batches])


def without_timing(x):
    """``x`` (metrics, nested) without the :data:`TIMING` keys."""
    if isinstance(x, dict):
        return {k: without_timing(v) for k, v in x.items() if k not in TIMING}
    if isinstance(x, list):
        return [without_timing(v) for v in x]
    return x


def assert_same(a, b) -> None:
    """``a`` and ``b`` (saved heads, nested) equal bit for bit, :data:`TIMING` keys aside."""
    if isinstance(a, torch.Tensor):
        assert torch.equal(a, b)
    elif isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            if k not in TIMING:
                assert_same(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert_same(x, y)
