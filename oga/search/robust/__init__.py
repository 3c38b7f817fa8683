"""Robust schedules over a machine's uncertainty set.

- :mod:`oga.search.robust.plants`: concrete plants drawn from the set (Monte Carlo and corners).
- :mod:`oga.verify.certificate`: a table and the fixed baseline replayed on every plant.
- :mod:`oga.search.robust.search`: the robust search (:func:`robust_optimize`).

:func:`oga.optimize.optimize` runs the robust search wherever the machine has an
uncertainty set, unless the ``nominal`` option is set. The names below load lazily.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

# name -> module that defines it
_EXPORTS = {
    "robust_optimize": "oga.search.robust.search",
    "RobustResult": "oga.search.robust.search",
    "certify": "oga.verify.certificate",
    "certify_result": "oga.verify.certificate",
    "Certificate": "oga.verify.certificate",
    "scenario_set": "oga.search.robust.plants",
    "ScenarioSet": "oga.search.robust.plants",
}

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
