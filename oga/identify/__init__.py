"""Identification of the axis model from a recorded trace (``oga excite``, ``oga identify``).

- :mod:`oga.identify.excite`: the identification program;
- :mod:`oga.identify.trace`: reading and checking traces (CSV, halsampler, TwinCAT Scope);
- :mod:`oga.identify.sim`: the simulator with its drive force, and synthetic traces;
- :mod:`oga.identify.fit`: the grey-box fit of one cascade axis;
- :mod:`oga.identify.write`: the identified machine file, with intervals and uncertainty.
"""

from __future__ import annotations

__all__ = ["identify", "excite_program", "read_trace", "load_trace", "Identification"]


def __getattr__(name: str):
    import importlib

    where = {"identify": "oga.identify.workflow", "Identification": "oga.identify.workflow",
             "excite_program": "oga.identify.excite", "read_trace": "oga.identify.trace",
             "load_trace": "oga.identify.trace"}
    if name not in where:
        raise AttributeError(f"module 'oga.identify' has no attribute {name!r}")
    return getattr(importlib.import_module(where[name]), name)
