"""Gain laws for controllers that adapt their own gains (Heidenhain MAC, TwinCAT CNC dynamic
Kv, LinuxCNC ``lincurve``): Kp and Kf as functions of the commanded ``|v|`` and ``|a|``.

- :mod:`oga.law.law`: the law (support points and values), its evaluation, its resolution.
- :mod:`oga.law.override`: programs replanned at a feed override.
- :mod:`oga.law.baseline`: the robust baseline a law is judged against.
- :mod:`oga.law.gradient`: derivatives of a replay along the support values.
- :mod:`oga.law.search`: the search (:func:`search_law`), robust, at every override.
- :mod:`oga.law.certificate`: the certificate on every program and override.
- :mod:`oga.law.export`: the controllers' files.
- :mod:`oga.law.run`: programs in, a certified law out (:func:`law_optimize`).

The names below load lazily.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

_EXPORTS = {
    "Law": "oga.law.law",
    "AxisLaw": "oga.law.law",
    "law_gains": "oga.law.law",
    "search_law": "oga.law.search",
    "LawResult": "oga.law.search",
    "Program": "oga.law.search",
    "certify_law": "oga.law.certificate",
    "law_optimize": "oga.law.run",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
