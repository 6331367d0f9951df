"""The one migration of old configs (files, checkpoints, results folders:
:func:`migrate_config_data`; overrides: :func:`migrate_overrides`) to the current schema, each
change with a deprecation line; :mod:`.loader` runs it on everything it loads."""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import fields
from typing import Any

from omegaconf import DictConfig, OmegaConf

from taskvar_torch.config.schema import Config
from taskvar_torch.contract import FAMILIES

ANY = object()
"""A :data:`REMOVED_KEYS` value: the key is dropped whatever it holds."""

_INFORMED_GONE = (
    "the informed baseline is an agent of its own on its own stream now, not a head of the "
    "learner: taskvar train-baselines --method informed (docs/memory.md)"
)

REMOVED_KEYS = {
    "train.switching": (
        "intra",
        "it had one allowed value: the switching head always learns by intra-option Q-learning",
    ),
    "heads.informed": (ANY, _INFORMED_GONE),
    "heads.informed_anchor": (ANY, _INFORMED_GONE),
}
"""Config keys that are gone -> ``(the one value an old config could hold, or ANY, why it
went)`` (docs/changelog.md, issues 45 and 56). An old config, checkpoint or override holding one
at that value (at any value: ``ANY``) loads without it, with a deprecation line; another value
is a one-line ``ValueError``."""


def _drop_removed(out: dict, source: str) -> list[str]:
    """Delete the :data:`REMOVED_KEYS` from the plain config dict ``out``; what was dropped."""
    what = []
    for dotted, (value, why) in REMOVED_KEYS.items():
        section, key = dotted.split(".")
        node = out.get(section)
        if isinstance(node, Mapping) and key in node:
            if value is not ANY and node[key] != value:
                raise ValueError(
                    f"{dotted}={node[key]!r} ({source}) cannot load: {dotted} was removed ({why})"
                )
            out[section] = {k: v for k, v in node.items() if k != key}
            what.append(f"{dotted} is dropped ({why})")
    return what


def _families(out: dict) -> tuple[Any, list]:
    """The family of the plain config dict ``out`` and every family whose declaration a
    migration reads (an installed plugin is imported only for its own configs)."""
    family = out.get("family", Config.family)
    known = FAMILIES.loaded()
    if isinstance(family, str) and family not in known and family in FAMILIES:
        known[family] = FAMILIES[family]
    return family, list(known.values())


def _move_env_keys(out: dict) -> list[str]:
    """The families' old spellings of their env keys in the plain config dict ``out`` migrated
    in place (:func:`migrate_config_data`); what changed."""
    env = out.get("env")
    if not isinstance(env, Mapping):
        return []
    family, families = _families(out)
    stale = [f.name for f in families if f.legacy_section and f.name in env and f.name != family]
    moved = {f.name: [p for p in legacy_paths(f).items() if _held(out, p[0])] for f in families}
    moved = {name: paths for name, paths in moved.items() if paths}
    if not stale and not moved:
        return []
    out["env"] = dict(env)
    what = []
    for name in stale:
        del out["env"][name]
        what.append(f"env.{name} is dropped (read only for family {name!r})")
    for name, paths in moved.items():
        legacy = {}
        for old, key in paths:
            section, old_key = old.split(".")
            out[section] = dict(out[section])
            legacy[key] = out[section].pop(old_key)
        first = paths[0][0]
        if name == family:
            out["env"][name] = {**legacy, **dict(out["env"].get(name) or {})}
            what.append(
                f"{first} and the other {name} keys are now env.{name}.* (moved)"
                if len(paths) > 1
                else f"{first} is now env.{name}.{paths[0][1]} (moved)"
            )
            continue
        for section in dict.fromkeys(old.split(".")[0] for old, _ in paths):
            keys = [old.split(".")[1] for old, _ in paths if old.startswith(section + ".")]
            what.append(f"the {name} keys at {section}.* ({', '.join(keys)}) are dropped")
    return what


def _drop_other_experiment_keys(out: dict) -> list[str]:
    """Another family's experiment keys (``experiment.trials`` in a windy config: every config
    held them until the experiments' keys moved into their families) dropped from the plain
    config dict ``out``; what was dropped."""
    x = out.get("experiment")
    if not isinstance(x, Mapping):
        return []
    family, families = _families(out)
    own = next((experiment_keys(f) for f in families if f.name == family), set())
    what = []
    for f in families:
        gone = [k for k in x if k in experiment_keys(f) - own] if f.name != family else []
        if gone:
            x = {k: v for k, v in x.items() if k not in gone}
            what.append(
                f"the {f.experiment.name} keys at experiment.* ({', '.join(gone)}) are dropped"
            )
    out["experiment"] = x
    return what


def experiment_keys(fam: Any) -> set[str]:
    """The own keys of ``fam``'s experiment (``Experiment.config_class``), read at ``experiment.*``."""
    cls = fam.experiment.config_class if fam.experiment is not None else None
    return {f.name for f in fields(cls)} if cls is not None else set()


def legacy_paths(fam: Any) -> dict[str, str]:
    """The old spellings of ``fam``'s env keys (``Family.legacy_env_keys``) as dotted paths ->
    the key of ``env.<name>`` each is now: ``layout`` was ``env.layout``, a dotted entry
    (``train.composed_reward``) its own path."""
    return {(k if "." in k else f"env.{k}"): k.rpartition(".")[2] for k in fam.legacy_env_keys}


def _held(out: Mapping, dotted: str) -> bool:
    """Whether the plain config dict ``out`` holds the two-part key ``dotted``."""
    section, key = dotted.split(".")
    return isinstance(out.get(section), Mapping) and key in out[section]


def migrate_config_data(data: Any, source: str = "config", warn: bool = True) -> Any:
    """Migrate old config ``data`` to the current schema, one deprecation line (``FutureWarning``
    unless ``warn`` is false) per config changed: :data:`REMOVED_KEYS` dropped; a family's
    ``legacy_env_keys`` moved to ``env.<name>.*`` in its configs and dropped in others; another
    family's ``legacy_section`` and experiment keys dropped (docs/families.md). Unchanged otherwise.
    """
    if not isinstance(data, (Mapping, DictConfig)):
        return data
    out = OmegaConf.to_container(data) if isinstance(data, DictConfig) else dict(data)
    what = _drop_removed(out, source) + _move_env_keys(out) + _drop_other_experiment_keys(out)
    if not what:
        return data
    if warn:
        family = out.get("family", Config.family)
        warnings.warn(
            f"{source}: written by an older taskvar_torch, family {family!r}: {'; '.join(what)}",
            FutureWarning,
            stacklevel=3,
        )
    return OmegaConf.create(out) if isinstance(data, DictConfig) else out


RENAMED_KEYS = {
    "baseline.mlp": "heads.hidden",
    "baseline.lr": "train.lr",
    "baseline.updates_per_batch": "train.updates_per_batch",
    "baseline.target_tau": "train.target_tau",
}
"""Old override keys -> the key they are now (the baselines read the heads' settings: their old
``baseline.*`` copies of them, ``taskvar train-baselines baseline.KEY=V``)."""


def migrate_overrides(overrides: Sequence[str], family: str | None = None) -> list[str]:
    """``overrides`` with every renamed key (:data:`RENAMED_KEYS`) spelt as it is now and every
    removed one (:data:`REMOVED_KEYS`) left out, each with a deprecation line (a
    ``FutureWarning``); ``baseline.mlp=64+64`` becomes
    ``heads.hidden=[64,64]``, and a family's ``legacy_env_keys`` (``env.layout=X``,
    ``train.composed_reward=sum``) their ``env.<name>.*`` spelling in a config of that ``family``
    (another family's is a one-line ``ValueError``). A malformed old value is a one-line ``ValueError`` naming it."""
    out = []
    for item in overrides:
        key, sep, value = str(item).partition("=")
        if sep and key.strip() in REMOVED_KEYS:
            section, name = key.strip().split(".")
            _drop_removed({section: {name: value.strip()}}, f"override {item!r}")  # or an error
            warnings.warn(
                f"{key.strip()} is deprecated: {REMOVED_KEYS[key.strip()][1]}; the override is "
                "ignored, remove it",
                FutureWarning,
                stacklevel=3,
            )
            continue
        owner, now = next(
            (
                (n, legacy_paths(f)[key.strip()])
                for n, f in FAMILIES.loaded().items()
                if key.strip() in legacy_paths(f)
            ),
            (None, None),
        )
        if sep and owner is not None:
            if family != owner:
                raise ValueError(
                    f"{key.strip()} is a {owner} key (env.{owner}.{now}); this config's family "
                    f"is {family!r}"
                )
            warnings.warn(
                f"{key.strip()} is deprecated: the {owner} family's keys are env.{owner}.*; use "
                f"env.{owner}.{now}={value}",
                FutureWarning,
                stacklevel=3,
            )
            out.append(f"env.{owner}.{now}={value}")
            continue
        new = RENAMED_KEYS.get(key.strip())
        if not sep or new is None:
            out.append(item)
            continue
        if key.strip() == "baseline.mlp":
            parts = [p.strip() for p in value.split("+") if p.strip()]
            if not all(p.isdigit() and int(p) > 0 for p in parts):
                raise ValueError(
                    f"baseline.mlp={value!r} must be widths joined by '+' (e.g. 64+64); it is "
                    "now heads.hidden, e.g. heads.hidden=[64,64]"
                )
            value = "[" + ",".join(parts) + "]"
        warnings.warn(
            f"{key.strip()} is deprecated: the baselines read the heads' setting {new}; "
            f"use {new}={value}",
            FutureWarning,
            stacklevel=3,
        )
        out.append(f"{new}={value}")
    return out
