"""``check_family``: does a family honour the contract every command relies on? What it checks, in
order, is docs/families.md#what-check_family-checks; the first miss is a one-line ``ValueError``,
a failure of a user's code inside the family a one-line ``UserCodeError``
(:mod:`taskvar_torch.guest`).
"""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import check_env_specs

from taskvar_torch import keys
from taskvar_torch.config.loader import config_schema
from taskvar_torch.contract import Family, check_declaration
from taskvar_torch.guest import UserCodeError
from taskvar_torch.subtasks.base import Subtasks

_STEPS = 24  # steps of the batch-split and subtask checks
_RESUME_STEPS = 8  # steps before the resume check's partial reset, and after it to the save
_RESUME_MAX_STEPS = 256  # the resume check steps min(horizon, this) + 1 steps after the load


def _fail(fam: Family, what: str) -> ValueError:
    return ValueError(f"family {fam.name!r}: {what} (docs/families.md)")


def _actions(t: int, index: torch.Tensor, num_actions: int) -> torch.Tensor:
    """A deterministic action per sub-environment that depends on its global index only."""
    return (index * 7 + t * 3) % num_actions


def _rollout(env, steps: int, offset: int) -> list[TensorDictBase]:
    """``steps`` steps of ``env`` (auto-reset), actions keyed by the global sub-env index."""
    n = env.batch_size[0]
    index = torch.arange(n, device=env.device) + offset
    num_actions = int(env.action_spec.space.n)
    td = env.reset()
    out = []
    for t in range(steps):
        td.set(keys.ACTION, _actions(t, index, num_actions).reshape(env.action_spec.shape))
        stepped, td = env.step_and_maybe_reset(td)
        out.append(stepped.clone())
    return out


def check_family(fam: Family, num_envs: int = 4) -> None:
    """Check that ``fam`` honours the family contract (docs/families.md#what-check_family-checks).

    Args:
        fam: the family, registered or not (an unregistered one is registered for the check; its
            name must be free).
        num_envs: the batch size of the N>1 checks (at least 2).

    Raises:
        ValueError: one line naming the first part of the contract ``fam`` misses.
    """
    from taskvar_torch.contract import FAMILIES, register_family

    check_declaration(fam)
    if "train" not in fam.instance_names:
        raise _fail(fam, "instance_names must include 'train' (the default of env.instances)")
    registered = FAMILIES._families.get(fam.name)
    if registered is not fam:  # checked under its name (an installed family's new object too)
        register_family(fam, replace=True)
    try:
        _check(fam, max(2, int(num_envs)))
    finally:
        if registered is None:
            FAMILIES._families.pop(fam.name, None)
        elif registered is not fam:  # the registered one back, as it was
            FAMILIES._families[fam.name] = registered


def _check(fam: Family, n: int) -> None:
    try:
        cfg = config_schema(fam.name)(family=fam.name)
    except ValueError as e:
        raise _fail(fam, f"its default config is refused: {e}") from None
    # specs at N=1 and N>1
    for size in (1, n):
        try:
            env = fam.make_env(cfg, size, seed=0)
        except UserCodeError:  # its own line: the family, the function, where
            raise
        except Exception as e:
            raise _fail(fam, f"env_class(**env_kwargs(cfg)) failed at num_envs={size}: {e}") from e
        if tuple(env.batch_size) != (size,):
            raise _fail(fam, f"the env's batch_size must be ({size},), got {tuple(env.batch_size)}")
        try:
            check_env_specs(env, seed=None)
        except UserCodeError:
            raise
        except Exception as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise _fail(fam, f"check_env_specs fails at num_envs={size}: {msg}") from None
    # the observation and the hidden instance
    td = env.reset()
    if keys.OBSERVATION not in td.keys():
        raise _fail(fam, f"the env must write {keys.OBSERVATION!r}")
    if (
        not isinstance(td.get(keys.INSTANCE, None), TensorDictBase)
        or td.get(keys.INSTANCE).is_empty()
    ):
        raise _fail(fam, f"the env must write the hidden instance under ({keys.INSTANCE!r}, ...)")
    obs = td.get(keys.OBSERVATION)
    if obs.dim() != 2 or not obs.is_floating_point():
        raise _fail(fam, f"{keys.OBSERVATION!r} must be float (N, D), got {tuple(obs.shape)}")
    # the horizon
    horizon = getattr(env, "horizon", None)
    if not isinstance(horizon, int) or horizon < 1:
        raise _fail(fam, f"the env must have an int .horizon >= 1, got {horizon!r}")
    # keyed seeding: sub-envs 1.. of a batch equal a batch starting at index_offset=1
    whole = _rollout(fam.make_env(cfg, n, seed=3), _STEPS, 0)
    part = _rollout(fam.make_env(cfg, n - 1, seed=3, index_offset=1), _STEPS, 1)
    for t, (a, b) in enumerate(zip(whole, part)):
        for key in (keys.OBSERVATION, (keys.NEXT, keys.OBSERVATION), (keys.NEXT, keys.REWARD)):
            if not torch.equal(a.get(key)[1:], b.get(key)):
                raise _fail(
                    fam,
                    f"{key} at step {t} changes with the batch split: sub-environment i must draw "
                    "from the key (seed, index_offset + i) alone",
                )
    if fam.resumable:
        _check_resume(fam, cfg, n)
    # the subtasks: names and shapes on a transition batch
    subtasks = fam.subtasks(cfg, env)
    if not isinstance(subtasks, Subtasks) or not subtasks.names:
        raise _fail(fam, "subtasks(cfg, env) must return a Subtasks with at least one option")
    batch = torch.stack(whole, 0).reshape(-1)  # (steps * n,)
    B, O = batch.shape[0], subtasks.num_options  # noqa: E741
    for what, value, dtype in (
        ("initiation", subtasks.initiation(batch), torch.bool),
        ("termination", subtasks.termination(batch.get(keys.NEXT)), torch.bool),
        ("reward", subtasks.reward(batch), None),
    ):
        if tuple(value.shape) != (B, O) or (dtype is not None and value.dtype != dtype):
            raise _fail(
                fam,
                f"Subtasks.{what} must be ({B}, {O})"
                + (" bool" if dtype else "")
                + f", got {tuple(value.shape)} {value.dtype}",
            )
    if subtasks.hierarchy is not None:
        unknown = sorted(set(subtasks.hierarchy.options) - set(subtasks.names))
        if unknown:
            raise _fail(fam, f"the hierarchy names options that do not exist: {unknown}")
    # the instance features
    if fam.instance_features is not None:
        z = fam.instance_features(batch)
        if z is None or tuple(z.shape) != (B, fam.instance_dim):
            got = None if z is None else tuple(z.shape)
            raise _fail(fam, f"instance_features must give ({B}, {fam.instance_dim}), got {got}")
    # the informed baseline's features (docs/memory.md)
    if fam.informed_features is not None:
        dim, feats = fam.informed_features(cfg)
        z = feats(batch)
        if z is None or tuple(z.shape) != (B, int(dim)):
            got = None if z is None else tuple(z.shape)
            raise _fail(fam, f"informed_features(cfg) must give ({B}, {dim}), got {got}")
    # the named test distributions build their envs
    if not fam.tests:
        raise _fail(fam, "tests must name at least one test distribution (taskvar eval --test)")
    from taskvar_torch.experiments.shift import shift_points

    for name in fam.tests:
        try:
            for point in shift_points(cfg, name):
                fam.make_env(point.cfg, 1, seed=0, instances=point.instances).reset()
        except UserCodeError:
            raise
        except Exception as e:
            raise _fail(fam, f"test distribution {name!r} does not build: {e}") from None


def _check_resume(fam: Family, cfg, n: int) -> None:
    """Exact resume as ``taskvar train --resume`` does it: an env saved mid-episode and loaded into
    a fresh one must step alike; a miss names the attributes that differ after the load."""
    g = torch.Generator().manual_seed(0)
    env = fam.make_env(cfg, n, seed=5)
    A, shape, T = int(env.action_spec.space.n), env.action_spec.shape, _RESUME_STEPS
    S = min(env.horizon, _RESUME_MAX_STEPS) + 1  # steps after the load

    def action() -> torch.Tensor:
        return torch.randint(A, shape, generator=g).to(env.device)

    half = torch.arange(n, device=env.device) % 2 == 0
    td = env.reset()
    for t in range(2 * T):
        if t == T:  # a partial reset: sub-envs 0, 2, ... start a new episode
            td = env.reset(td.set("_reset", half.reshape(env.done_spec.shape)))
        _, td = env.step_and_maybe_reset(td.set(keys.ACTION, action()))
    saved = copy.deepcopy(env.state_dict())
    fresh = fam.make_env(cfg, n, seed=6)
    fresh.reset()
    try:
        fresh.load_state_dict(saved)
    except Exception as e:
        raise _fail(fam, f"env.load_state_dict(other.state_dict()) fails: {e}") from None
    unsaved = _differing_state(env, fresh, n)
    twin = td.clone()
    for t in range(1, S + 1):
        a = action()
        try:
            outputs = []
            for e, x in ((env, td), (fresh, twin)):
                if t == S // 2:  # a partial reset: sub-envs 1, 3, ... start anew
                    x = e.reset(x.set("_reset", ~half.reshape(e.done_spec.shape)))
                outputs.append(e.step_and_maybe_reset(x.set(keys.ACTION, a.clone())))
            (out, td), (out_twin, twin) = outputs
            differs = [k for k in out.keys(True, True) if not _same(out[k], out_twin.get(k, None))]
        except UserCodeError:
            raise
        except Exception as e:
            differs = [f"an error ({type(e).__name__}: {e})"]
        if not differs:
            continue
        what = f"{differs[0]} differs at step {t} after the load"
        if unsaved:
            names = ", ".join(repr(name) for name in unsaved)
            raise _fail(
                fam,
                f"env state {names} {'is' if len(unsaved) == 1 else 'are'} not saved for "
                f"resume: add {'it' if len(unsaved) == 1 else 'them'} to runtime_state "
                f"(an env loaded from another's state_dict() mid-episode: {what})",
            )
        raise _fail(
            fam,
            f"an env loaded from another's state_dict() mid-episode steps differently ({what}): "
            "some state is not saved for resume (runtime_state, get_runtime_state)",
        )


def _same(a, b) -> bool:
    return isinstance(b, torch.Tensor) and a.shape == b.shape and torch.equal(a, b)


def _differing_state(env, fresh, n: int) -> list[str]:
    """Attributes of ``env`` (tensors ``(n, ...)``, or tuples of them: ``name.field``) that
    ``fresh`` lacks or holds with other values."""
    found = []
    for name, value in vars(env).items():
        other = vars(fresh).get(name)
        if isinstance(value, torch.Tensor):
            if value.dim() and value.shape[0] == n and not _same(value, other):
                found.append(name)
        elif (
            isinstance(value, tuple)
            and value
            and all(isinstance(v, torch.Tensor) and v.dim() and v.shape[0] == n for v in value)
        ):
            fields = getattr(value, "_fields", range(len(value)))
            others = other if isinstance(other, tuple) and len(other) == len(value) else ()
            for i, (field, v) in enumerate(zip(fields, value)):
                if not _same(v, others[i] if others else None):
                    found.append(f"{name}.{field}")
    return found


__all__ = ["check_family"]
