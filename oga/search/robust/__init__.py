"""Robust schedules over a machine's uncertainty set.

- :mod:`oga.robust.plants`: concrete plants drawn from the set (Monte Carlo and corners).
- :mod:`oga.robust.certificate`: a table and the fixed baseline replayed on every plant.
- :mod:`oga.robust.search`: the robust search (:func:`robust_optimize`).

:func:`oga.optimize.optimize` runs the robust search wherever the machine has an
uncertainty set, unless the ``nominal`` option is set. The names below load lazily.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

# name -> module that defines it
_EXPORTS = {
    "robust_optimize": "oga.robust.search",
    "RobustResult": "oga.robust.search",
    "certify": "oga.robust.certificate",
    "certify_result": "oga.robust.certificate",
    "Certificate": "oga.robust.certificate",
    "scenario_set": "oga.robust.plants",
    "ScenarioSet": "oga.robust.plants",
}

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
