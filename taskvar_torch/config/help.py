"""``--help`` text of a config schema, from the docstring below each field (docs/design.md, Configs).

A field's docstring is the string literal right below it in the dataclass body (PEP 257's
"attribute docstring"). Python discards such literals at runtime, so :func:`field_docs` reads them
back from the class source with the standard library's :mod:`ast`. A library that does the same
(``simple_parsing``, ``docstring_parser``'s attribute docs, ``tyro``) would be a new dependency
and a different CLI for this one small function, which is why none is used.

Examples:
    >>> field_docs(Config)["seed"]
    'Master seed of environments, networks and exploration.'
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import typing

from taskvar_torch.config.schema import Config


def field_docs(cls: type) -> dict[str, str]:
    """The docstring below each field of a config dataclass, by field name (whitespace folded;
    class constants such as ``ClassVar`` annotations are not fields and are left out)."""
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


def config_help(cls: type = Config, prefix: str = "") -> str:
    """``--help`` text: one line per dotted key with its type, default and docstring.

    A nested dataclass field is a header line followed by its own keys; ``cls`` may be any
    config dataclass whose fields all have defaults. For :class:`Config`, every registered
    family's own keys (``Family.config_class``, under ``env.<name>``) follow.
    """
    lines = []
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    default = cls()
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t):
            lines.append(f"{prefix}{f.name}: {docs.get(f.name, '')}")
            lines.append(config_help(t, f"{prefix}{f.name}."))
            continue
        value = getattr(default, f.name)
        shown = list(value) if isinstance(value, tuple) else value
        tname = t.__name__ if isinstance(t, type) else str(t).replace("typing.", "")
        lines.append(f"  {prefix}{f.name} ({tname}, default {shown!r}): {docs.get(f.name, '')}")
    if cls is Config and not prefix:  # each registered family's own keys, read for it only
        from taskvar_torch.families import FAMILIES

        for name in sorted(FAMILIES):
            section = FAMILIES[name].config_class
            if section is not None:
                lines.append(f"env.{name}: the {name} family's own keys (read when family={name})")
                lines.append(config_help(section, f"env.{name}."))
    return "\n".join(lines)
