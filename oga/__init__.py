"""oga: offline gain-schedule optimizer for CNC machine tools.

The public API is imported lazily, so ``import oga`` stays cheap and the
compiled kernels load only when used.
"""

from __future__ import annotations

import importlib
import sys
import types

from oga._jitcache import configure as _configure_jit_cache
from oga._lazy import lazy_exports

_configure_jit_cache()  # before any kernel module imports numba

__version__ = "0.1.0"

# name -> module that defines it
_EXPORTS = {
    "Machine": "oga.model.machine",
    "load_machine": "oga.model.machine",
    "OptimizeOptions": "oga.options",
    "OptimizeResult": "oga.search.result",
    "optimize": "oga.optimize",
    "run_job": "oga.pipeline",
    "simulate": "oga.model.response",
    "stable_range": "oga.model.stability",
    "gain_ranges": "oga.search.ranges",
    "contour_error": "oga.model.contour",
    "OgaError": "oga.errors",
    "InputError": "oga.errors",
    "GcodeError": "oga.errors",
    "ToolpathError": "oga.errors",
    "MachineError": "oga.errors",
    "OptionError": "oga.errors",
    "PlanError": "oga.errors",
    "OptimizeError": "oga.errors",
    "TuneError": "oga.errors",
}

#: Submodules a library user reaches as ``oga.<name>`` without importing them first
#: (``oga.export.table_csv(result)``), name -> module; loaded on first use, like the names
#: above. ``compare``, ``machine`` and ``ranges`` are the names they had before the tree of
#: issue 31 (``oga.controllers.compare``, ``oga.model.machine``, ``oga.search.ranges``).
_SUBMODULES = {
    "compare": "oga.controllers.compare",
    "controllers": "oga.controllers",
    "defaults": "oga.defaults",
    "export": "oga.export",
    "identify": "oga.identify",
    "machine": "oga.model.machine",
    "model": "oga.model",
    "options": "oga.options",
    "pipeline": "oga.pipeline",
    "ranges": "oga.search.ranges",
    "report": "oga.report",
    "search": "oga.search",
    "verify": "oga.verify",
}

__all__ = sorted(_EXPORTS) + ["identify", "__version__"]


_export = lazy_exports(globals(), _EXPORTS)[0]


def __getattr__(name: str):
    if name in _SUBMODULES:
        module = importlib.import_module(_SUBMODULES[name])
        globals()[name] = module  # bound here (a subpackage's import binds only its own name)
        return module
    return _export(name)


def __dir__():
    return sorted(set(__all__) | set(_SUBMODULES))


class _Package(types.ModuleType):
    """``oga``: the functions ``optimize`` and ``simulate`` keep their names when their
    submodules (``oga.optimize``, ``oga.simulate``) are imported, which would otherwise
    bind the submodule in their place."""

    def __setattr__(self, name: str, value) -> None:
        if name in _EXPORTS and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
