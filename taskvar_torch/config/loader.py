"""Strict loading of config dataclasses with OmegaConf structured configs (docs/design.md#configs).

One pipeline for every schema (:func:`load_strict`): YAML merged into
``OmegaConf.structured(schema)``, ``key.sub=value`` overrides on top, then the frozen dataclass,
whose ``__post_init__`` checks ranges and choices. An unknown key or wrong type is a one-line
``ValueError`` naming the dotted key (and the closest allowed one); range errors name their source.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import os
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import field, fields
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from taskvar_torch.config.migration import (
    experiment_keys,
    legacy_paths,
    migrate_config_data,
    migrate_overrides,
)
from taskvar_torch.config.schema import Config, EnvConfig, ExperimentConfig, experiment_class
from taskvar_torch.contract import FAMILIES, family
from taskvar_torch.io import atomic_write

T = TypeVar("T")

_LIST_ITEM = "a list is set whole (e.g. {key}=[...]); its items cannot be set one by one"


# --------------------------------------------------------------------------------------------
# families that bring their own env keys (env.<family name>)


def config_schema(family_name: str | None = None) -> type[Config]:
    """The :class:`Config` schema of family ``family_name``'s configs: :class:`Config`, or a
    subclass holding ``Family.config_class`` under ``env.<name>`` and ``Experiment.config_class``
    under ``experiment`` (docs/families.md); made once per family, pickles as its dict."""
    if family_name is None:  # the schema's default family
        family_name = Config.family
    fam = family(family_name)  # an unknown family is a one-line error naming the known ones
    section = fam.config_class
    if section is not None and family_name in {f.name for f in fields(EnvConfig)}:
        section = None
    experiment = experiment_class(family_name)
    if section is None and experiment is ExperimentConfig:
        return Config
    return _schema_with_sections(family_name, section, experiment)


@functools.cache
def _schema_with_sections(
    name: str, section_class: type | None, experiment: type[ExperimentConfig]
) -> type[Config]:
    """``Config`` whose ``env`` has the field ``name: section_class`` (range checks deferred to
    the validation, which names ``env.<name>.<field>``, as for ``env.wargus``) and whose
    ``experiment`` is ``experiment``."""
    sections = [("experiment", experiment, field(default_factory=experiment))]
    if section_class is not None:
        unchecked = dataclasses.make_dataclass(
            section_class.__name__,
            [],
            bases=(section_class,),
            frozen=True,
            namespace={"__post_init__": lambda self: None, "__module__": section_class.__module__},
        )
        env_class = dataclasses.make_dataclass(
            "EnvConfig",
            [(name, unchecked, field(default_factory=unchecked))],
            bases=(EnvConfig,),
            frozen=True,
            namespace={"__module__": __name__},
        )
        sections.append(("env", env_class, field(default_factory=env_class)))
    return dataclasses.make_dataclass(
        "Config",
        sections,
        bases=(Config,),
        frozen=True,
        namespace={"__module__": __name__, "__reduce__": _reduce_config, "_schema_family": name},
    )


def _reduce_config(cfg: Config) -> tuple:
    """Pickle a family-section config as its dict (the class is made at run time): it is rebuilt,
    and validated, where the same family is registered (an entry point, or the same import)."""
    return config_from_dict, (config_to_dict(cfg), "a pickled config")


# --------------------------------------------------------------------------------------------
# schema lookups


@functools.cache
def _structured(schema: type) -> DictConfig:
    """A writable OmegaConf node of ``schema`` with its defaults (unknown keys refused), built
    once per schema (``OmegaConf.structured`` is most of a config load's time). Shared: only ever
    the first argument of ``OmegaConf.merge``, which merges into a copy of it, never mutated."""
    node = OmegaConf.structured(schema)
    OmegaConf.set_readonly(node, False)
    return node


def _field_class(cls: type, name: str) -> type | None:
    """The dataclass a dotted-key part names in ``cls``: a section, or ``name[i]`` of a list of
    dataclasses; None otherwise."""
    base, _, index = name.partition("[")
    t = typing.get_type_hints(cls).get(base)
    if index:  # list[X] or tuple[X, ...]: the element's class
        args = [a for a in typing.get_args(t) if a is not Ellipsis]
        t = args[0] if len(args) == 1 else None
    return t if t is not None and dataclasses.is_dataclass(t) else None


def _schema_class(schema: type, dotted: str) -> type | None:
    """The dataclass that holds the last part of ``dotted`` (``train.lr`` -> TrainConfig)."""
    cls: type | None = schema
    for part in [p for p in dotted.split(".") if p][:-1]:
        cls = _field_class(cls, part)
        if cls is None:
            return None
    return cls


def _list_key(schema: type, dotted: str) -> str:
    """The first part of ``dotted`` that is not a section (``heads.hidden.0`` -> heads.hidden)."""
    parts = dotted.split(".")
    cls: type | None = schema
    for i, part in enumerate(parts):
        cls = _field_class(cls, part) if cls is not None else None
        if cls is None:
            return ".".join(parts[: i + 1])
    return dotted


def _first_non_mapping(node: Any, cls: type, prefix: str = "") -> str | None:
    """First dotted key whose value should be a section (mapping) but is not."""
    if not isinstance(node, Mapping):
        return None
    hints = typing.get_type_hints(cls)
    for k, v in node.items():
        t = hints.get(k)
        if t is not None and dataclasses.is_dataclass(t):
            if not isinstance(v, Mapping):
                return f"{prefix}{k}"
            found = _first_non_mapping(v, t, f"{prefix}{k}.")
            if found:
                return found
    return None


def _failing_leaf(schema: type, raw: Any) -> str | None:
    """The first dotted leaf of ``raw`` that fails to merge on its own (OmegaConf sometimes loses
    the key, e.g. for a bad list element)."""
    if not isinstance(raw, Mapping):
        return None

    def leaves(node: Mapping, prefix: str = ""):
        for k, v in node.items():
            if isinstance(v, Mapping) and v:
                yield from leaves(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    for dotted, value in leaves(raw):
        single: Any = value
        for part in reversed(dotted.split(".")):
            single = {part: single}
        try:
            OmegaConf.merge(_structured(schema), single)
        except (OmegaConfBaseException, TypeError):
            return dotted
    return None


def _raw_value(raw: Any, dotted: str) -> Any:
    """Value at ``dotted`` in a nested mapping, or None."""
    node = raw
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


# --------------------------------------------------------------------------------------------
# one-line errors


def _config_error(schema: type, e: Exception, source: str, raw: Any) -> ValueError:
    """Turn an OmegaConf error (or its ``TypeError`` for a list item set alone) into a one-line
    ValueError naming the dotted key; ``raw`` is the data whose merge failed (None: unknown)."""
    key = getattr(e, "full_key", None)
    first = (
        str(getattr(e, "msg", None) or e).strip().splitlines()[0]
        if str(e).strip()
        else type(e).__name__
    )
    if not key:
        key = _first_non_mapping(raw, schema)
        if key:
            cls = _schema_class(schema, key + ".x")
            return ValueError(
                f"config key {key!r} ({source}) must be a section of "
                f"{[f.name for f in dataclasses.fields(cls)]}, got {_raw_value(raw, key)!r}"
            )
        key = _failing_leaf(schema, raw)
        if not key:
            return ValueError(f"invalid config ({source}): {first}")
        if "$VALUE" in first:  # an unformatted OmegaConf template: "... converted to Integer"
            first = f"{_raw_value(raw, key)!r} could not be converted to {first.rsplit(' ', 1)[-1]}"
    if isinstance(e, TypeError):  # OmegaConf merging a mapping into a list
        first = _LIST_ITEM.format(key=_list_key(schema, key))
    leaf = key.split(".")[-1].partition("[")[0]
    cls = _schema_class(schema, key)
    allowed = [f.name for f in dataclasses.fields(cls)] if cls is not None else []
    object_type = getattr(e, "object_type", None)
    if cls is not None and leaf not in allowed:
        level = key.rsplit(".", 1)[0] if "." in key else "the top level"
        if dataclasses.is_dataclass(object_type) and object_type is not cls:
            # a key inside a list item: OmegaConf names the leaf and the item's class only
            cls, level = object_type, object_type.__name__
            allowed = [f.name for f in dataclasses.fields(cls)]
        hint = difflib.get_close_matches(leaf, allowed, n=1)
        mean = f" (did you mean {hint[0]!r}?)" if hint else ""
        return ValueError(
            f"unknown config key {key!r} ({source}){mean}; allowed keys in {level}: {', '.join(allowed)}"
        )
    return ValueError(f"bad value for config key {key!r} ({source}): {first}")


# --------------------------------------------------------------------------------------------
# the pipeline: file -> schema -> overrides -> frozen dataclass


def _read_yaml(path: Path) -> DictConfig:
    """The YAML mapping in ``path``; a missing file, bad YAML or a non-mapping is one line."""
    if not path.is_file():
        raise ValueError(f"config file {str(path)!r} does not exist")
    try:
        data = OmegaConf.load(path)
    except Exception as e:  # yaml.YAMLError and friends
        raise ValueError(
            f"config file {str(path)!r} is not valid YAML: {_yaml_problem(e)}"
        ) from None
    if not isinstance(data, DictConfig):
        raise ValueError(f"config file {str(path)!r} must hold a mapping, got a list")
    return data


def _yaml_problem(e: BaseException) -> str:
    """``line L, column C: problem`` of a YAML syntax error (1-based), else its first line."""
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    problem = getattr(e, "problem", None) or getattr(e, "context", None)
    if mark is not None and problem:
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def _merge(schema: type, base: DictConfig, update: Any, source: str) -> DictConfig:
    """``OmegaConf.merge(base, update)`` with its errors reworded (:func:`_config_error`)."""
    raw = OmegaConf.to_container(update) if isinstance(update, DictConfig) else update
    if not isinstance(raw, Mapping):
        raise ValueError(
            f"config ({source}) must be a mapping of keys to values, got {type(raw).__name__}"
        )
    try:
        return OmegaConf.merge(base, update)
    except (OmegaConfBaseException, TypeError) as e:
        raise _config_error(schema, e, source, raw) from None


def _to_object(schema: type[T], node: DictConfig, source: str) -> T:
    """The frozen dataclass of ``node``; its ``__post_init__`` errors get ``source`` appended."""
    try:
        cfg = OmegaConf.to_object(node)
    except OmegaConfBaseException as e:
        raise _config_error(schema, e, source, None) from None
    except ValueError as e:  # __post_init__: range and choice checks
        raise ValueError(f"{e} ({source})") from None
    assert isinstance(cfg, schema)
    return cfg


def _parse_override(schema: type, item: str) -> DictConfig:
    """``key.sub=value`` as an OmegaConf node; anything else (``+key``, ``~key``) is refused."""
    if not isinstance(item, str) or "=" not in item or item.startswith(("+", "~")):
        nested = any(dataclasses.is_dataclass(t) for t in typing.get_type_hints(schema).values())
        form = "key.sub=value" if nested else "key=value"
        example = getattr(schema, "override_example", None)
        raise ValueError(
            f"override {item!r} must look like {form}" + (f" (e.g. {example})" if example else "")
        )
    try:
        return OmegaConf.from_dotlist([item])
    except Exception as e:  # OmegaConf and YAML parse errors
        raise ValueError(f"override {item!r} cannot be parsed: {str(e).splitlines()[0]}") from None


def overrides_for(overrides: Sequence[str], family_name: str) -> list[str]:
    """The ``overrides`` that apply to a config of ``family_name``: another family's own keys
    (``env.<name>.*``, their old spellings, ``Family.legacy_env_keys``, and its experiment's
    ``experiment.*``) are left out. For overrides meant for configs of several families at once
    (the scale experiment's)."""
    known = FAMILIES.loaded()  # an unused plugin is not imported for this
    own = experiment_class(family_name)
    out = []
    for item in overrides:
        key = str(item).partition("=")[0].strip()
        part = key.split(".")
        owner = part[1] if len(part) > 2 and part[0] == "env" and part[1] in FAMILIES else None
        owner = owner or next((n for n, f in known.items() if key in legacy_paths(f)), None)
        if part[0] == "experiment" and len(part) == 2 and part[1] not in own.__dataclass_fields__:
            owner = next((n for n, f in known.items() if part[1] in experiment_keys(f)), owner)
        if owner is not None and owner != family_name:
            continue
        out.append(item)
    return out


def _apply_overrides(
    schema: type, node: DictConfig, overrides: Sequence[str], label: str = "override"
) -> DictConfig:
    """``node`` with the overrides merged in order (renamed keys migrated: :func:`migrate_overrides`);
    an error names the override (``label``)."""
    if isinstance(overrides, str):
        overrides = [overrides]
    if schema is Config or issubclass(schema, Config):
        env_fields = {f.name for f in fields(typing.get_type_hints(schema)["env"])}
        family = next((f for f in env_fields if f in FAMILIES), None)  # its section's family
        overrides = migrate_overrides(overrides, family)
    parsed = [_parse_override(schema, item) for item in overrides]
    if not parsed:
        return node
    try:  # one merge; on failure, redo them one by one to name the culprit
        return OmegaConf.merge(node, *parsed)
    except (OmegaConfBaseException, TypeError):
        for item, update in zip(overrides, parsed):
            node = _merge(schema, node, update, f"{label} {item!r}")
        return node


def load_strict(
    schema: type[T],
    path: str | os.PathLike,
    overrides: Sequence[str] = (),
    *,
    quick: bool = False,
    quick_overrides: Callable[[T], Sequence[str]] | None = None,
    check_quick: bool = True,
) -> T:
    """Load a YAML file into the config dataclass ``schema`` strictly, then apply overrides.

    Args:
        schema: a dataclass whose fields all have defaults; keys left out of the file take them.
            Its ``override_example`` class constant, if any, is shown for a malformed override.
        path: the YAML file.
        overrides: ``key.sub=value`` strings, applied in order after the file.
        quick: apply ``quick_overrides(config in the file)`` before ``overrides``.
        quick_overrides: where the file's quick overrides are (None: the schema has none).
        check_quick: without ``quick``, still check that the quick overrides apply, so a typo
            there fails now rather than in the next quick run.

    Returns:
        The frozen ``schema`` instance.

    Raises:
        ValueError: a missing file, an unknown key, a wrong type or a value out of range, in one
            line naming the dotted key.
    """
    path = Path(path)
    data = _read_yaml(path)
    if schema is Config:  # a family with its own env keys extends the schema (config_schema)
        data = migrate_config_data(data, str(path))
        schema = config_schema(_family_named(data.get("family", None), overrides))
    node = _merge(schema, _structured(schema), data, f"in {path}")
    cfg = _to_object(schema, node, f"in {path}")
    if quick_overrides is not None and quick:
        node = _apply_overrides(schema, node, quick_overrides(cfg), "quick override")
    elif quick_overrides is not None and check_quick:
        checked = _apply_overrides(schema, node.copy(), quick_overrides(cfg), "quick override")
        _to_object(schema, checked, "quick_overrides")
    node = _apply_overrides(schema, node, overrides)
    return _to_object(schema, node, f"in {path} with overrides")


# --------------------------------------------------------------------------------------------
# Config entry points (the dict and YAML ones take any config dataclass)


def load_config(
    path: str | os.PathLike, overrides: Sequence[str] = (), quick: bool = False
) -> Config:
    """Load a YAML config strictly, then apply ``key.sub=value`` overrides.

    Args:
        path: YAML file mirroring :class:`Config`; keys left out take the dataclass defaults.
        overrides: Hydra-style dotlist strings, applied in order after the file.
        quick: apply ``experiment.quick_overrides`` (before ``overrides``); without it they are
            still checked.

    Returns:
        The frozen :class:`Config`.

    Raises:
        ValueError: a missing file, an unknown key, a wrong type or a value out of range, in one
            line naming the dotted key.
    """
    return load_strict(
        Config,
        path,
        overrides,
        quick=quick,
        quick_overrides=lambda cfg: cfg.experiment.quick_overrides,
    )


def _family_named(family: Any, overrides: Sequence[str] = ()) -> str | None:
    """The ``family`` a config will have: the last ``family=NAME`` override, else ``family``."""
    if isinstance(overrides, str):
        overrides = [overrides]
    for item in overrides:
        key, sep, value = str(item).partition("=")
        if sep and key.strip() == "family":
            family = value.strip()
    return family if isinstance(family, str) else None


def apply_overrides(cfg: T, overrides: Sequence[str]) -> T:
    """``cfg`` (any config dataclass) with ``key.sub=value`` overrides applied (same strict
    errors)."""
    schema = type(cfg)
    if isinstance(cfg, Config):
        schema = config_schema(_family_named(cfg.family, overrides))
    # as plain data: a family-section schema (config_schema) is not the class of a plain Config;
    # a family=NAME override leaves the old family's section and experiment keys behind
    data = config_to_dict(cfg)
    if isinstance(cfg, Config):
        target = _family_named(cfg.family, overrides)
        data["env"] = {k: v for k, v in data["env"].items() if k not in FAMILIES or k == target}
        kept = {f.name for f in fields(typing.get_type_hints(schema)["experiment"])}
        data["experiment"] = {k: v for k, v in data["experiment"].items() if k in kept}
    node = _merge(schema, _structured(schema), OmegaConf.create(data), "config")
    return _to_object(schema, _apply_overrides(schema, node, overrides), "with overrides")


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict of str/int/float/bool/None/list (tuples become lists), e.g. for
    checkpoints; ``cfg`` is any config dataclass. A :class:`Config` built without its family's
    section (``Config(family=...)`` in code) gets the section's defaults, as the loader gives."""

    def plain(x: Any) -> Any:
        if isinstance(x, Mapping):
            return {k: plain(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [plain(v) for v in x]
        return x

    out = plain(OmegaConf.to_container(OmegaConf.structured(cfg), resolve=True))
    if isinstance(cfg, Config) and isinstance(out.get("env"), dict):  # a plain Config(...)
        fam = FAMILIES[cfg.family] if cfg.family in FAMILIES else None
        if fam is not None and fam.config_class is not None and cfg.family not in out["env"]:
            section = OmegaConf.structured(fam.config_class())  # its defaults, always written
            out["env"][cfg.family] = plain(OmegaConf.to_container(section, resolve=True))
    return out


def config_from_dict(
    d: Mapping[str, Any], source: str = "config dict", schema: type[T] = Config
) -> T:
    """Strictly rebuild a ``schema`` instance (a :class:`Config` by default) from
    :func:`config_to_dict` output (same errors as YAML)."""
    if not isinstance(d, Mapping):
        raise ValueError(f"config ({source}) must be a mapping, got {type(d).__name__}")
    if schema is Config:
        d = migrate_config_data(d, source)
        schema = config_schema(_family_named(d.get("family")))
    try:
        data = OmegaConf.create(dict(d))
    except OmegaConfBaseException as e:
        raise ValueError(f"config ({source}) is not plain data: {str(e).splitlines()[0]}") from None
    return _to_object(schema, _merge(schema, _structured(schema), data, source), source)


def config_to_yaml(cfg: Any) -> str:
    """YAML text of ``cfg`` (every key), loadable by :func:`load_config` (or :func:`load_strict`
    with its schema)."""
    return OmegaConf.to_yaml(OmegaConf.create(config_to_dict(cfg)))


def save_config_yaml(cfg: Any, path: str | os.PathLike) -> None:
    """Write ``cfg`` as YAML atomically (see :func:`~taskvar_torch.io.atomic_write`)."""
    text = config_to_yaml(cfg).encode()
    atomic_write(path, lambda f: f.write(text))
