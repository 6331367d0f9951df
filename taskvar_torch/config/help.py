"""``--help`` text of a config schema from the attribute docstring below each field
(docs/design.md#configs), read back from the class source with :mod:`ast`.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import re
import textwrap
import typing

from taskvar_torch.config.schema import Config


def field_docs(cls: type) -> dict[str, str]:
    """The docstring below each field of a config dataclass, by field name (whitespace folded;
    class constants such as ``ClassVar`` annotations are not fields and are left out)."""
    return dict(_field_docs(cls))


@functools.cache
def _field_docs(cls: type) -> dict[str, str]:
    """:func:`field_docs`, read once per class: every ``taskvar`` command builds the ``train``
    help (one line per key), and reading a class's source for each of its keys made that ~60%
    of a refused command's time."""
    fields = {f.name for f in dataclasses.fields(cls)}
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):  # a field's docstring may sit in a base dataclass
        if klass is object or not dataclasses.is_dataclass(klass):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        body = tree.body[0].body  # type: ignore[attr-defined]
        for stmt, nxt in zip(body, body[1:]):
            if (
                isinstance(stmt, ast.AnnAssign)
                and isinstance(stmt.target, ast.Name)
                and stmt.target.id in fields
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[stmt.target.id] = " ".join(nxt.value.value.split())
    return docs


USER_KEYS = (
    "family",
    "seed",
    "device",
    "env.num_envs",
    "env.instances",
    "env.windy.layout",
    "env.windy.obs_encoding",
    "env.windy.horizon",
    "heads.hidden",
    "heads.activation",
    "heads.network",
    "train.total_frames",
    "train.lr",
    "train.gamma",
    "train.batch_size",
    "train.buffer_size",
    "train.frames_per_batch",
    "train.updates_per_batch",
    "train.init_random_frames",
    "train.eps_decay_frames",
    "train.seeds",
    "train.checkpoint_every",
    "train.log_every",
    "train.compile",
    "train.eval_ema_tau",
    "collector.num_workers",
    "collector.backend",
    "eval.method",
    "eval.test",
    "eval.episodes",
    "experiment.runs",
    "experiment.quick_overrides",
    "baseline.hidden",
    "baseline.slice_len",
)
"""The keys ``taskvar train --help`` shows: those a user sets (what the shipped configs and the
docs change, and the budget); ``--help-all`` (:func:`config_help`) shows every key."""


@functools.cache
def _hints(cls: type) -> dict[str, typing.Any]:
    """``typing.get_type_hints(cls)``, once per class (the help is built by every command)."""
    return typing.get_type_hints(cls)


@functools.cache
def _key_line(cls: type, name: str, prefix: str) -> str:
    """``  prefix.name (type, default value): docstring`` of field ``name`` of ``cls`` (once per
    key: a class's fields, defaults and docstrings do not change within a process)."""
    t = _hints(cls)[name]
    value = getattr(cls(), name)
    shown = list(value) if isinstance(value, tuple) else value
    tname = t.__name__ if isinstance(t, type) else str(t).replace("typing.", "")
    return f"  {prefix}{name} ({tname}, default {shown!r}): {field_docs(cls).get(name, '')}"


def config_help(cls: type = Config, prefix: str = "") -> str:
    """``--help-all`` text: one line per dotted key (type, default, docstring), nested dataclasses
    as headers; for :class:`Config`, every family's ``env.<name>`` and experiment keys follow."""
    lines = []
    docs = field_docs(cls)
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            lines.append(f"{prefix}{f.name}: {docs.get(f.name, '')}")
            lines.append(config_help(hints[f.name], f"{prefix}{f.name}."))
            continue
        lines.append(_key_line(cls, f.name, prefix))
    if cls is Config and not prefix:  # each registered family's own keys, read for it only
        from taskvar_torch.contract import FAMILIES

        known = FAMILIES.loaded()  # an installed plugin is named, not imported
        for name in sorted(known):
            section = known[name].config_class
            if section is not None:
                lines.append(f"env.{name}: the {name} family's own keys (read when family={name})")
                lines.append(config_help(section, f"env.{name}."))
            exp = known[name].experiment
            if exp is not None and exp.config_class is not None:
                lines.append(f"experiment: {exp.name}'s own keys (read when family={name})")
                lines.append(config_help(exp.config_class, "experiment."))
        for name, value in sorted(FAMILIES.entry_points().items()):
            lines.append(f"env.{name}: {unloaded_plugin(name, value)}")
    return "\n".join(lines)


def key_line(cls: type, key: str) -> str:
    """``  key (type, default value): docstring`` of the dotted ``key`` of ``cls`` (a family's own
    section, ``env.<name>``, read from the registry)."""
    *path, name = key.split(".")
    for part in path:
        hints = _hints(cls)
        if part in hints:
            cls = hints[part]
        else:  # a family's own section, env.<name>
            from taskvar_torch.contract import FAMILIES

            cls = FAMILIES[part].config_class
    return _key_line(cls, name, "".join(p + "." for p in path))


def user_help() -> str:
    """``--help`` text: the :data:`USER_KEYS`, one line each, under their section's header."""
    lines, section = [], None
    for key in USER_KEYS:
        header = key.rpartition(".")[0] or "top level"
        if header != section:
            section = header
            lines.append(f"{header}:")
        lines.append(key_line(Config, key))
    return "\n".join(lines)


def families_help() -> str:
    """One line per registered family (read from the registry, installed families included): its
    description, instance distributions (``env.instances``), tests (``eval.test``) and own keys
    (``env.<name>.*``, documented by ``--help-all``)."""
    from taskvar_torch.contract import FAMILIES

    lines = []
    for name, fam in FAMILIES.loaded().items():
        own = [f.name for f in dataclasses.fields(fam.config_class)] if fam.config_class else []
        exp = fam.experiment.config_class if fam.experiment is not None else None
        parts = [
            f"env.instances {', '.join(fam.instance_names)}",
            f"eval.test {', '.join(fam.tests)}",
            f"own keys env.{name}.{{{', '.join(own)}}}" if own else "no own keys",
        ]
        if exp is not None:
            x = ", ".join(f.name for f in dataclasses.fields(exp))
            parts.append(f"{fam.experiment.name} keys experiment.{{{x}}}")
        about = f"{fam.description}; " if fam.description else ""
        lines.append(f"  {name}: {about}" + "; ".join(parts))
    lines += [f"  {n}: {unloaded_plugin(n, v)}" for n, v in sorted(FAMILIES.entry_points().items())]
    return "\n".join(lines)


def unloaded_plugin(name: str, value: str) -> str:
    """A listing's line for an installed family not imported (a listing imports no plugin: one
    that hangs or crashes on import cannot take ``--help`` down)."""
    return f"installed from {value!r}, not imported by a listing (read when family={name})"


def count_keys(text: str) -> int:
    """Keys listed in a help text of :func:`config_help` or :func:`user_help`."""
    return sum(1 for line in text.splitlines() if re.match(r"  [a-z][a-z0-9_.]* \(", line))
