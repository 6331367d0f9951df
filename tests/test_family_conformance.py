"""The family contract (docs/families.md), one suite for every family: each registered family
(windy, wargus, taxi and any installed one) and the outside example (``examples/corridor``) runs
:func:`~taskvar_torch.check_family` and the contract checks it leaves to the tests: seeding,
``noise_seed``, exact resume, refused actions, the named instance distributions, per-transition
subtasks, the heads built from the registry entry, and every declared Gymnasium id.

A family's own behaviour (its dynamics against a reference, its rendering, its oracle) stays in
its own test file."""

from __future__ import annotations

import dataclasses
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from tensordict import TensorDictBase

import taskvar_torch  # noqa: F401  (registers every family's Gymnasium ids)
from taskvar_torch import check_family, keys
from taskvar_torch.config.loader import config_schema
from taskvar_torch.factory import HeadSpec, build_heads
from taskvar_torch.families import FAMILIES, family, register_family

torch.set_num_threads(1)
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "corridor"
sys.path.insert(0, str(EXAMPLE))  # the example's module, without installing it
import taskvar_corridor as corridor  # noqa: E402

EXAMPLE_NAME = (
    "corridor_example"  # registered under a name of its own (an installed copy is left be)
)
NAMES = [*sorted(FAMILIES), EXAMPLE_NAME]
GYM_IDS = [(name, i) for name in sorted(FAMILIES) for i in FAMILIES[name].gym_ids]
N, STEPS = 6, 48


@pytest.fixture(scope="module", params=NAMES)
def fam(request):
    """Each family, the example registered for the module's duration."""
    if request.param != EXAMPLE_NAME:
        yield family(request.param)
        return
    example = register_family(dataclasses.replace(corridor.family(), name=EXAMPLE_NAME))
    yield example
    FAMILIES._families.pop(EXAMPLE_NAME, None)


@pytest.fixture(scope="module")
def cfg(fam):
    """The family's default config (what ``check_family`` builds from)."""
    return config_schema(fam.name)(family=fam.name)


def _actions(env, steps: int, seed: int) -> torch.Tensor:
    """Random actions ``(steps, N)`` within the env's action space."""
    n = int(env.action_spec.space.n)
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, n, (steps, env.num_envs), generator=g)


def _rollout(
    env, actions: torch.Tensor, td: TensorDictBase | None = None
) -> tuple[TensorDictBase, TensorDictBase]:
    """Every transition ``(T, N)`` of ``env`` under ``actions`` with auto-reset (from ``td``, or
    a reset), and the tensordict to continue from."""
    td = env.reset() if td is None else td
    out = []
    for a in actions:
        stepped, td = env.step_and_maybe_reset(td.set(keys.ACTION, a))
        out.append(stepped.clone())
    return torch.stack(out, 0), td


def _equal(a: TensorDictBase, b: TensorDictBase) -> bool:
    """Same keys and bit-identical leaves."""
    ka = set(a.keys(True, True))
    return ka == set(b.keys(True, True)) and all(torch.equal(a.get(k), b.get(k)) for k in ka)


def test_check_family(fam):
    check_family(fam)


def test_same_seed_same_episodes_another_seed_other_instances(fam, cfg):
    actions = _actions(fam.make_env(cfg, N), STEPS, seed=0)
    a, _ = _rollout(fam.make_env(cfg, N, seed=4), actions)
    b, _ = _rollout(fam.make_env(cfg, N, seed=4), actions)
    c, _ = _rollout(fam.make_env(cfg, N, seed=5), actions)
    assert _equal(a, b)
    assert not _equal(a.get(keys.INSTANCE), c.get(keys.INSTANCE))


def test_noise_seed_keeps_the_instances_and_starts(fam, cfg):
    """docs/families.md: ``noise_seed`` salts the per-step noise, never the instance or start
    (paired evaluation's common random numbers); a family without per-step noise apart from the
    instance (Wargus) refuses a non-zero one in one line."""
    a = fam.make_env(cfg, N, seed=3, noise_seed=0).reset()
    try:
        b = fam.make_env(cfg, N, seed=3, noise_seed=1).reset()
    except ValueError as e:
        assert "noise_seed" in str(e) and "\n" not in str(e)
        return
    assert _equal(a.exclude(keys.INSTANCE), b.exclude(keys.INSTANCE))
    assert _equal(a.get(keys.INSTANCE), b.get(keys.INSTANCE))


def test_state_dict_continues_the_episodes_exactly(fam, cfg):
    """Exact resume: a fresh env of another seed, loading ``a.state_dict()``, continues ``a``'s
    episodes bit for bit (a family declared ``resumable=False`` makes no such claim)."""
    if not fam.resumable:
        pytest.skip(f"family {fam.name!r} is declared resumable=False")
    a = fam.make_env(cfg, N, seed=3)
    actions = _actions(a, 2 * STEPS, seed=1)
    _, td = _rollout(a, actions[:STEPS])
    b = fam.make_env(cfg, N, seed=99)
    b.reset()
    b.load_state_dict(a.state_dict())
    ours, _ = _rollout(a, actions[STEPS:], td.clone())
    theirs, _ = _rollout(b, actions[STEPS:], td.clone())
    assert _equal(ours, theirs)


def test_an_action_out_of_range_is_refused_in_one_line(fam, cfg):
    env = fam.make_env(cfg, 2, validate_actions=True)
    td = env.reset()
    td.set(keys.ACTION, torch.tensor([0, int(env.action_spec.space.n)]))
    with pytest.raises(ValueError, match="action") as e:
        env.step(td)
    assert "\n" not in str(e.value)


def test_every_named_instance_distribution_stays_within_the_specs(fam, cfg):
    for name in fam.instance_names:
        env = fam.make_env(cfg, N, seed=1, instances=name)
        steps, _ = _rollout(env, _actions(env, 8, seed=2))
        spec = env.full_observation_spec
        for t in range(steps.shape[0]):
            nxt = steps[t].get(keys.NEXT)
            assert spec.is_in(nxt.select(*spec.keys(True, True))), (name, t)


def test_subtasks_are_computed_per_transition(fam, cfg):
    """Each row of ``initiation``, ``termination`` and ``reward`` depends on its own transition
    only: a permuted batch gives the permuted rows."""
    env = fam.make_env(cfg, N, seed=2)
    batch = _rollout(env, _actions(env, STEPS, seed=3))[0].reshape(-1)
    subtasks = fam.subtasks(cfg, env)
    perm = torch.randperm(batch.shape[0], generator=torch.Generator().manual_seed(0))
    shuffled = batch[perm]
    for what, f in (
        ("initiation", lambda td: subtasks.initiation(td)),
        ("termination", lambda td: subtasks.termination(td.get(keys.NEXT))),
        ("reward", lambda td: subtasks.reward(td)),
    ):
        assert torch.equal(f(batch)[perm], f(shuffled)), what
    assert bool(subtasks.initiation(batch).any(-1).all()), "a state where no option can start"


def test_heads_build_from_the_registry_entry(fam, cfg):
    env = fam.make_env(cfg, 3, seed=5)
    assert isinstance(env, fam.env_class) and tuple(env.batch_size) == (3,)
    subtasks = fam.subtasks(cfg, env)
    spec = HeadSpec.of(cfg, env, subtasks)
    assert spec.option_names == tuple(subtasks.names)
    assert spec.num_actions == int(env.action_spec.space.n)
    assert HeadSpec.from_dict(spec.to_dict()) == spec
    heads = build_heads(cfg, spec)
    obs = env.reset()[keys.OBSERVATION]
    assert heads.heads["options"].module(obs).shape == (3, len(subtasks.names), spec.num_actions)


# ----------------------------------------------------------------- the declared Gymnasium ids


@pytest.mark.parametrize(("name", "env_id"), GYM_IDS)
def test_gym_id_passes_check_env_without_a_warning(name, env_id):
    assert env_id in gym.registry
    for mode in (None, "ansi", "rgb_array"):
        env = gym.make(env_id, render_mode=mode)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env.unwrapped, skip_render_check=mode is None)
        assert not caught, [str(w.message) for w in caught]


@pytest.mark.parametrize(("name", "env_id"), GYM_IDS)
@pytest.mark.parametrize("mode", ["ansi", "rgb_array"])
def test_gym_id_renders(name, env_id, mode):
    env = gym.make(env_id, render_mode=mode)
    env.reset(seed=0)
    frame = env.render()
    if mode == "ansi":
        assert isinstance(frame, str) and len(frame.splitlines()) >= 4
    else:
        assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3
        assert frame.shape[2] == 3 and frame.shape[0] >= 64 and frame.std() > 0


@pytest.mark.parametrize(("name", "env_id"), GYM_IDS)
def test_gym_id_same_seed_same_trajectory_another_seed_another(name, env_id):
    def play(seed):
        env = gym.make(env_id)
        obs, _ = env.reset(seed=seed)
        out, acts = [obs], np.random.default_rng(0).integers(0, env.action_space.n, 200)
        for a in acts:
            obs, r, term, trunc, _ = env.step(int(a))
            out.append(obs)
            if term or trunc:
                obs, _ = env.reset()
                out.append(obs)
        return np.stack(out)

    a, b, c = play(1), play(1), play(2)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
