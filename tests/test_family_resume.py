"""Exact resume in the family contract (docs/families.md, "The env"): an env declares in
``runtime_state`` what ``env.state_dict()`` saves, and ``check_family`` round-trips an env's
state mid-episode and names a state left out (issue 46)."""

from __future__ import annotations

import copy
import dataclasses
import sys
from pathlib import Path

import pytest
import torch

from taskvar_torch import check_family, family, keys
from taskvar_torch.envs.batched import BatchedFamilyEnv
from taskvar_torch.families.wargus.env import WargusEnv

torch.set_num_threads(1)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "corridor"))
import taskvar_corridor as corridor  # noqa: E402


class _NoCell(corridor.CorridorEnv):
    """The audit's corridor: ``_cell`` left out of what a checkpoint saves."""

    runtime_state = tuple(s for s in corridor.CorridorEnv.runtime_state if s != "_cell")


def _steps_that_differ(env_class, steps: int = 40, n: int = 4) -> int:
    """Sub-env steps (of ``steps * n``) that differ between an env and one loaded from its
    ``state_dict()`` mid-episode, under the same actions."""
    g = torch.Generator().manual_seed(0)
    env = env_class(num_envs=n, seed=1)
    td = env.reset()
    for _ in range(5):
        _, td = env.step_and_maybe_reset(td.set(keys.ACTION, torch.randint(2, (n,), generator=g)))
    fresh = env_class(num_envs=n, seed=1)
    fresh.reset()
    fresh.load_state_dict(copy.deepcopy(env.state_dict()))
    twin, differ = td.clone(), 0
    for _ in range(steps):
        a = torch.randint(2, (n,), generator=g)
        x, td = env.step_and_maybe_reset(td.set(keys.ACTION, a))
        y, twin = fresh.step_and_maybe_reset(twin.set(keys.ACTION, a.clone()))
        differ += int((x["next", keys.CELL] != y["next", keys.CELL]).sum())
    return differ


def test_a_loaded_env_continues_exactly_and_one_missing_a_state_does_not():
    assert _steps_that_differ(corridor.CorridorEnv) == 0
    assert _steps_that_differ(_NoCell) > 0


def test_check_family_names_the_state_left_out_of_runtime_state():
    fam = dataclasses.replace(corridor.family(), name="hall5", env_class=_NoCell)
    with pytest.raises(ValueError, match=r"env state '_cell' is not saved for resume") as e:
        check_family(fam)
    assert "\n" not in str(e.value) and "runtime_state" in str(e.value)


def test_check_family_names_the_fields_of_a_tuple_state_left_out(monkeypatch):
    """Wargus without its override that saves the ``WargusState`` tuple."""
    monkeypatch.setattr(WargusEnv, "get_runtime_state", BatchedFamilyEnv.get_runtime_state)
    monkeypatch.setattr(WargusEnv, "set_runtime_state", BatchedFamilyEnv.set_runtime_state)
    with pytest.raises(ValueError, match=r"'_state\.agent'.* are not saved for resume"):
        check_family(family("wargus"))


def test_the_saved_keys_are_the_names_without_the_underscore():
    """Checkpoints written before the rename keep loading: the extra state's keys are unchanged."""
    env = corridor.CorridorEnv(num_envs=2)
    env.reset()
    state = env.get_extra_state()
    assert set(state) == {"base_key", "episode", "key", "t", "cell", "goal", "slip", "seed"}


def test_the_names_before_issue_46_still_work_with_a_future_warning():
    with pytest.warns(FutureWarning, match="_RUNTIME_STATE is deprecated"):

        class OldNames(corridor.CorridorEnv):
            _RUNTIME_STATE = ("_base_key", "_episode", "_cell")

    assert OldNames.runtime_state == ("_base_key", "_episode", "_cell")
    env = corridor.CorridorEnv(num_envs=2)
    with pytest.warns(FutureWarning, match="_make_done_spec is deprecated"):
        env._make_done_spec()
    with pytest.warns(FutureWarning, match="_next_episodes is deprecated"):
        idx, key = env._next_episodes(None, started=False)
    assert idx is None and key.shape == (2,)
    with pytest.warns(FutureWarning, match="_set_state is deprecated; use replace_state"):
        env._set_state({"_cell": torch.ones(2, dtype=torch.int64)})
    assert env._cell.tolist() == [1, 1]
    with pytest.warns(FutureWarning, match="_finish is deprecated"):
        td = env._finish({keys.CELL: env._cell})
    assert not td[keys.DONE].any()
