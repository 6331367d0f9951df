"""Test distributions and shifts of a trained bundle's family (``taskvar eval --test --shift``).

A test point is the bundle's config with some ``env`` keys changed and an instance distribution;
:func:`shift_points` builds them from a named test distribution and shifts ``env.KEY=VALUE``,
``env.instances.FIELD=VALUE`` or ``KEY=V1,V2,V3`` (a shift curve), each validated
(docs/evaluation.md#the---shift-grammar).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import yaml

from taskvar_torch.config import Config, apply_overrides
from taskvar_torch.contract import Family, family

INSTANCE_PREFIX = "env.instances."


@dataclass(frozen=True)
class Shift:
    """One ``--shift KEY=V1[,V2,...]``: the key and its value(s)."""

    key: str
    values: tuple[str, ...]


@dataclass(frozen=True)
class EvalPoint:
    """One evaluation's environment: ``cfg`` (the bundle's, env keys shifted) and ``instances``.

    ``label`` is ``""`` without a swept key, else ``KEY=VALUE`` of the swept key; ``value`` its
    value (a string, as given)."""

    label: str
    value: str | None
    cfg: Config
    instances: Any


def parse_shift(item: str) -> Shift:
    """``"KEY=V1,V2"`` -> :class:`Shift`; a one-line ``ValueError`` for a malformed item."""
    key, sep, values = item.partition("=")
    key = key.strip()
    vals = tuple(v.strip() for v in values.split(","))
    if not sep or not key or not all(vals):
        raise ValueError(
            f"--shift must be KEY=VALUE or KEY=V1,V2,... (e.g. env.p=0.5), got {item!r}"
        )
    if not key.startswith("env."):
        raise ValueError(
            f"--shift changes env keys only (env.KEY or {INSTANCE_PREFIX}FIELD), got {key!r}"
        )
    return Shift(key, vals)


def _test_distribution(fam: Family, test: str | None) -> tuple[str, Any]:
    names = list(fam.tests)
    if not names:
        raise ValueError(
            f"family {fam.name!r} names no test distributions (Family.tests), so its bundles "
            "cannot be evaluated (docs/families.md)"
        )
    name = names[0] if test is None else test
    if name not in fam.tests:
        raise ValueError(f"--test must be one of {names} for a {fam.name} bundle, got {test!r}")
    return name, fam.tests[name]


def _apply(fam: Family, cfg: Config, fields: dict[str, Any], key: str, value: str):
    """``cfg`` and instance ``fields`` with ``key=value`` applied."""
    if key == "env.instances":  # a whole named distribution
        return cfg, _instance_fields(fam, value, key)
    if key.startswith(INSTANCE_PREFIX):
        name = key[len(INSTANCE_PREFIX) :]
        allowed = sorted({*fields, *fam.shift_aliases})
        if fam.make_instances is None:
            raise ValueError(f"--shift {key}: family {fam.name!r} instances cannot be shifted")
        if name not in allowed:
            raise ValueError(
                f"--shift {key}: {fam.name} instance fields are {allowed}, got {name!r}"
            )
        return cfg, {**fields, name: _scalar(value)}
    try:
        return apply_overrides(cfg, [f"{key}={value}"]), fields
    except ValueError as e:
        raise ValueError(f"--shift {key}={value}: {e}") from None


def _scalar(value: str) -> Any:
    """``value`` as YAML reads a scalar: int, float, bool or null, else the string itself."""
    try:
        v = yaml.safe_load(value)
    except yaml.YAMLError:
        return value
    return v if isinstance(v, (int, float, bool)) or v is None else value


def _instance_fields(fam: Family, spec: Any, key: str = "--test") -> dict[str, Any]:
    if fam.instance_fields is None:
        return {"name": spec}
    try:
        return fam.instance_fields(spec)
    except ValueError as e:
        raise ValueError(f"{key}: {e}") from None


def _instances(fam: Family, fields: dict[str, Any], where: str) -> Any:
    if fam.make_instances is None:
        return fields.get("name")
    try:
        return fam.make_instances({k: v for k, v in fields.items() if v is not None})
    except (TypeError, ValueError) as e:
        raise ValueError(f"--shift {where}: {e}") from None


def shift_points(cfg: Config, test: str | None, shifts: Sequence[Shift] = ()) -> list[EvalPoint]:
    """The test points of the named distribution ``test`` of ``cfg``'s family (``None``: the
    family's first) with ``shifts`` applied; one point per value of the swept key (at most one
    shift may hold several values)."""
    fam = family(cfg)
    name, dist = _test_distribution(fam, test)
    base = cfg
    for item in dist.overrides:
        key, _, value = item.partition("=")
        base, _ = _apply(fam, base, {}, key, value)
    fields = _instance_fields(fam, dist.instances)
    swept = [s for s in shifts if len(s.values) > 1]
    if len(swept) > 1:
        raise ValueError(f"--shift sweeps one key at a time, got several: {[s.key for s in swept]}")
    point_cfg, point_fields = base, fields
    for s in shifts:
        if len(s.values) == 1:
            point_cfg, point_fields = _apply(fam, point_cfg, point_fields, s.key, s.values[0])
    fixed = ",".join(f"{s.key}={s.values[0]}" for s in shifts if len(s.values) == 1)
    if not swept:
        return [EvalPoint("", None, point_cfg, _instances(fam, point_fields, fixed or name))]
    out = []
    for value in swept[0].values:
        c, f = _apply(fam, point_cfg, point_fields, swept[0].key, value)
        label = f"{swept[0].key}={value}"
        out.append(EvalPoint(label, value, c, _instances(fam, f, label)))
    return out


__all__ = ["Shift", "EvalPoint", "parse_shift", "shift_points"]
