"""The gain search: which gains are allowed, and the schedule within them.

- :mod:`oga.search.ranges`: the allowed gain ranges and the best fixed gains;
- :mod:`oga.search.paper`: the paper's mode (candidates per sample);
- :mod:`oga.search.window`: the windowed (receding-horizon) search;
- :mod:`oga.search.robust`: the robust search over a machine's uncertainty set;
- :mod:`oga.search.result`: what a search returns (:class:`GainSchedule`,
  :class:`OptimizeResult`).

:func:`oga.optimize` runs them. The names below load lazily.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

# name -> module that defines it
_EXPORTS = {
    "gain_ranges": "oga.search.ranges",
    "best_fixed_gains": "oga.search.ranges",
    "GainSchedule": "oga.search.result",
    "OptimizeResult": "oga.search.result",
    "robust_optimize": "oga.search.robust.search",
}
_SUBMODULES = ("ranges", "paper", "window", "robust", "result")

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS, _SUBMODULES)
