"""The REST service of oga (FastAPI): durable optimisation jobs on SQLite, run by worker processes.

Start it with ``oga serve``; build it in code with :func:`create_app`. The names
are imported lazily, so the CLI can read the store's defaults without FastAPI.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

_EXPORTS = {
    "Settings": "api.app",
    "create_app": "api.app",
    "Store": "api.store",
    "WorkerPool": "api.workers",
}

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
