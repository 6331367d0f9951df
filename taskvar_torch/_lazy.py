"""Names a package hands on but imports only on first use (PEP 562's module ``__getattr__``), so
``import taskvar_torch`` reads the families' declarations and not what they hand on."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from importlib import import_module
from typing import Any


def lazy_names(
    namespace: dict[str, Any], table: Mapping[str, str | tuple[str, str]]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """A module's ``__getattr__`` and ``__dir__`` for the names of ``table`` (name -> module, or
    ``(module, name there)``): a name is imported when first asked for, then kept in
    ``namespace`` (the module's ``globals()``)."""

    def __getattr__(name: str) -> Any:
        spec = table.get(name)
        if spec is None:
            raise AttributeError(f"module {namespace['__name__']!r} has no attribute {name!r}")
        module, attr = spec if isinstance(spec, tuple) else (spec, name)
        value = getattr(import_module(module), attr)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted([*namespace, *table])

    return __getattr__, __dir__
