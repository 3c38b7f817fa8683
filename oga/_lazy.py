"""Lazy package attributes: ``package.name`` imports its defining module on first use."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_exports(namespace: dict, exports: dict[str, str],
                 submodules: tuple[str, ...] = ()) -> tuple[Callable, Callable]:
    """The module ``__getattr__`` and ``__dir__`` of a package whose ``exports`` (name ->
    defining module) load on first use and are then bound in ``namespace`` (its globals);
    ``package.<submodule>`` for a name in ``submodules`` imports that submodule."""
    package = namespace["__name__"]

    def __getattr__(name: str):
        if name in submodules:
            return importlib.import_module(f"{package}.{name}")  # the import binds it
        try:
            module = exports[name]
        except KeyError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value
        return value

    def __dir__():
        return sorted(exports) + sorted(submodules)

    return __getattr__, __dir__
