"""``gym_family``: a task family from a Gymnasium env id or a ``make(instance)`` callable
(docs/gymnasium.md). Its own config keys live under ``env.NAME`` (:class:`GymConfig`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import torch

from taskvar_torch import keys
from taskvar_torch.contract import Family, TestDistribution, one_of
from taskvar_torch.families.gymnasium.encoder import SpaceEncoder
from taskvar_torch.families.gymnasium.env import VECTOR, GymFamilyEnv
from taskvar_torch.families.gymnasium.instances import Instances, reset_seed
from taskvar_torch.families.gymnasium.options import GymHierarchySubtasks, GymSubtasks, Option
from taskvar_torch.families.gymnasium.sub_env import INSTANCE_VIA
from taskvar_torch.subtasks.base import Hierarchy


@dataclass(frozen=True)
class GymConfig:
    """A Gymnasium family's own keys (``env.NAME.*``)."""

    vector: str = "sync"
    """``sync``: ``gymnasium.vector.SyncVectorEnv``; ``async``: ``AsyncVectorEnv`` (one process
    per sub-environment)."""
    horizon: int = 0
    """Steps before truncation; 0: the family's (``gym_family(horizon=...)``, else the env id's
    ``max_episode_steps``). The env's own truncation ends an episode earlier."""

    def __post_init__(self):
        one_of("vector", self.vector, VECTOR)
        if int(self.horizon) < 0:
            raise ValueError(f"horizon must be >= 0 (0: the family's), got {self.horizon}")


@dataclass(frozen=True)
class GymAdapter:
    """Everything the env of a Gymnasium family needs from the user (built by :func:`gym_family`)."""

    make: str | Callable[[dict], gym.Env]
    instances: Instances
    instance_via: str
    options: tuple[Option, ...]
    encoder: Callable[[gym.Space], Any]
    state_info: Callable[[gym.Env], dict] | None
    instance_info: Mapping[str, Callable[[gym.Env], float]]
    horizon: int
    reset_seed: Callable[[int], int] = reset_seed
    apply: Callable[[gym.Env, dict], None] | None = None
    hierarchy: Hierarchy | None = None
    name: str = "gymnasium"
    """The family's name, in every one-line failure of the user's code (:mod:`taskvar_torch.guest`)."""

    @property
    def instance_keys(self) -> tuple[str, ...]:
        """The ``("instance", NAME)`` entries: the drawn parameters, then those read after reset."""
        return self.instances.keys + tuple(self.instance_info)


def _instance_features(names: tuple[str, ...]) -> Callable[[Any], torch.Tensor]:
    def features(td) -> torch.Tensor:
        return torch.stack([td.get((keys.INSTANCE, k)).to(torch.float32) for k in names], -1)

    return features


def _hierarchy(spec: Mapping[str, Any] | Hierarchy | None, options: Sequence[Option]):
    """The declared hierarchy, checked against the options: a one-line ``ValueError`` naming an
    unknown option or one without a ``robustness`` function."""
    if spec is None:
        return None
    tree = spec if isinstance(spec, Hierarchy) else Hierarchy.from_dict(dict(spec))
    by_name = {o.name: o for o in options}
    unknown = [n for n in tree.options if n not in by_name]
    if unknown:
        raise ValueError(
            f"hierarchy names {unknown[0]!r}, which is not an option; the options: {list(by_name)}"
        )
    bare = [n for n in tree.options if by_name[n].robustness is None]
    if bare:
        raise ValueError(
            f"hierarchy option {bare[0]!r} has no robustness function: give Option(..., "
            "robustness=fn(obs, info, reward) -> float) to every option of the hierarchy"
        )
    return tree


def gym_family(
    name: str,
    make: str | Callable[[dict], gym.Env],
    instances: Mapping[str, Any],
    options: Sequence[Option],
    *,
    instance_via: str = "kwargs",
    encoder: Callable[[gym.Space], Any] = SpaceEncoder,
    state_info: Callable[[gym.Env], dict] | None = None,
    instance_info: Mapping[str, Callable[[gym.Env], float]] | None = None,
    horizon: int | None = None,
    tests: Mapping[str, TestDistribution] | None = None,
    description: str = "",
    apply: Callable[[gym.Env, dict], None] | None = None,
    hierarchy: Mapping[str, Any] | Hierarchy | None = None,
) -> Family:
    """A :class:`~taskvar_torch.families.Family` of Gymnasium envs
    (docs/gymnasium.md#what-you-give-gym_family).

    Args:
        name: the family's name (the config's ``family``; its keys under ``env.NAME``).
        make: a Gymnasium env id, or ``make(instance) -> gym.Env``.
        instances: the named instance distributions (``train`` required), ``sample(rng) -> dict``.
        options: the options (:class:`Option`).
        instance_via: ``kwargs``, ``attributes`` (set on ``env.unwrapped``) or ``options``
            (``reset(options=instance)``).
        encoder: ``space -> encoder`` of the observation (default :class:`SpaceEncoder`).
        state_info: ``env.unwrapped -> dict``, merged into the info the options read.
        instance_info: ``NAME -> f(env.unwrapped) -> number``, read after each reset and written
            under ``("instance", NAME)``.
        horizon: steps before truncation (default: the env id's ``max_episode_steps``).
        tests: the ``taskvar eval --test`` distributions (default: one per named one).
        description: one line for listings.
        apply: ``apply(env.unwrapped, instance)`` for ``instance_via="attributes"`` (default:
            ``setattr`` of each key).
        hierarchy: ``{"root": NAME, "children": {NAME: [NAMES]}}`` (paper §3.4.2); each of its
            options needs a ``robustness`` function.

    Returns the family, ``resumable=False``.
    """
    one_of("instance_via", instance_via, INSTANCE_VIA)
    if apply is not None and (instance_via != "attributes" or not callable(apply)):
        raise ValueError(
            f"apply must be a function (env, instance) -> None, with instance_via='attributes'; "
            f"got apply={apply!r}, instance_via={instance_via!r}"
        )
    options = tuple(options)
    if not options or not all(isinstance(o, Option) for o in options):
        raise ValueError("options must be a non-empty sequence of Option")
    names = [o.name for o in options]
    if len(set(names)) != len(names):
        raise ValueError(f"option names must be distinct, got {names}")
    if horizon is None:
        steps = gym.spec(make).max_episode_steps if isinstance(make, str) else None
        if steps is None:
            raise ValueError(
                f"gym_family {name!r}: give horizon= (the env has no max_episode_steps)"
            )
        horizon = int(steps)
    if int(horizon) < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    tree = _hierarchy(hierarchy, options)
    named = Instances(instances, family=name)
    instance_info = dict(instance_info or {})
    clash = sorted(set(instance_info) & set(named.keys))
    if clash or not all(callable(f) for f in instance_info.values()):
        raise ValueError(
            f"instance_info must map new names to functions of the env, got {sorted(instance_info)}"
            f" (drawn parameters: {list(named.keys)})"
        )
    adapter = GymAdapter(
        make=make,
        instances=named,
        instance_via=instance_via,
        options=options,
        encoder=encoder,
        state_info=state_info,
        instance_info=instance_info,
        horizon=int(horizon),
        apply=apply,
        hierarchy=tree,
        name=name,
    )
    if tests is None:
        tests = {
            k: TestDistribution(f"instances {k!r}", k)
            for k in dict.fromkeys(("train", *named.names))
        }

    def section(cfg) -> GymConfig:
        return getattr(cfg.env, name, None) or GymConfig()

    def env_kwargs(cfg) -> dict[str, Any]:
        own = section(cfg)
        return {
            "adapter": adapter,
            "num_envs": cfg.env.num_envs,
            "instances": cfg.env.instances,
            "seed": cfg.seed,
            "vector": own.vector,
            "horizon": own.horizon,
            "device": cfg.device,
        }

    shiftable = named.fields_class is not None
    given = tuple(o.policy is not None for o in options)
    return Family(
        name=name,
        description=description or f"Gymnasium env {make if isinstance(make, str) else name}",
        env_class=GymFamilyEnv,
        env_kwargs=env_kwargs,
        subtasks=lambda cfg, env: (
            GymSubtasks(tuple(names), given)
            if tree is None
            else GymHierarchySubtasks(tuple(names), given, tree)
        ),
        instance_names=named.names,
        config_class=GymConfig,
        tests=dict(tests),
        instance_fields=named.fields if shiftable else None,
        make_instances=named.make if shiftable else None,
        instance_dim=len(adapter.instance_keys),
        instance_features=_instance_features(adapter.instance_keys),
        resumable=False,
    )


__all__ = ["GymAdapter", "GymConfig", "gym_family"]
