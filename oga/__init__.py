"""oga: offline gain-schedule optimizer for CNC machine tools.

The public API is imported lazily, so ``import oga`` stays cheap and the
compiled kernels load only when used.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# name -> module that defines it
_EXPORTS = {
    "Machine": "oga.machine",
    "load_machine": "oga.machine",
    "OptimizeOptions": "oga.options",
    "OptimizeResult": "oga.optimize",
    "optimize": "oga.optimize",
    "run_job": "oga.pipeline",
    "simulate": "oga.simulate",
    "stable_range": "oga.stability",
    "gain_ranges": "oga.ranges",
    "contour_error": "oga.contour",
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

__all__ = sorted(_EXPORTS) + ["identify", "__version__"]


#: Subpackages reached as attributes (``oga.identify(...)``: the package is callable).
_SUBPACKAGES = ("identify",)


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        return importlib.import_module(f"oga.{name}")
    try:
        module = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'oga' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__
