"""The REST service of oga (FastAPI): durable optimisation jobs on SQLite, run by worker processes.

Start it with ``oga serve``; build it in code with :func:`create_app`. The names
are imported lazily, so the CLI can read the store's defaults without FastAPI.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Settings": "api.app",
    "create_app": "api.app",
    "Store": "api.storage",
    "WorkerPool": "api.workers",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    try:
        module = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'api' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__
