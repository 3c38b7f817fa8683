"""Identification of the axis model from a recorded trace (``oga excite``, ``oga identify``).

- :mod:`oga.identify.excite`: the identification program;
- :mod:`oga.identify.trace`: reading and checking traces (CSV, halsampler, TwinCAT Scope);
- :mod:`oga.identify.sim`: the simulator with its drive force, and synthetic traces;
- :mod:`oga.identify.fit`: the grey-box fit of one cascade axis;
- :mod:`oga.identify.write`: the identified machine file, with intervals and uncertainty;
- :mod:`oga.identify.workflow`: :func:`identify`, the whole fit;
- :mod:`oga.identify.report`: the HTML report.

The package itself is callable: ``oga.identify(trace, machine, ...)`` is
:func:`oga.identify.workflow.identify`.
"""

from __future__ import annotations

import importlib
import sys
import types

__all__ = ["identify", "excite_program", "read_trace", "load_trace", "Identification"]

_WHERE = {"identify": "oga.identify.workflow", "Identification": "oga.identify.workflow",
          "excite_program": "oga.identify.excite", "read_trace": "oga.identify.trace",
          "load_trace": "oga.identify.trace"}


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'oga.identify' has no attribute {name!r}")
    return getattr(importlib.import_module(_WHERE[name]), name)


class _CallableModule(types.ModuleType):
    def __call__(self, *args, **kwargs):
        """:func:`oga.identify.workflow.identify`."""
        return importlib.import_module("oga.identify.workflow").identify(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
