"""The plant model: what a machine is and how it answers a command.

- :mod:`oga.model.machine`: the machine file (axes, cascades, limits, uncertainty set);
- :mod:`oga.model.linear`, :mod:`oga.model.stability`: the linear loop, its stable gain range;
- :mod:`oga.model.simulate`, :mod:`oga.model.tangent`: compiled simulation of the loops
  (and its tangent for the gradient search);
- :mod:`oga.model.plant`: a machine packed once for the kernels (and a batch of them);
  :mod:`oga.model.response`: every axis of a plant simulated on setpoints;
- :mod:`oga.model.kinematics`, :mod:`oga.model.contour`, :mod:`oga.model.metrics`: command
  derivatives and their limits, the contour error, its figures.

The names below load lazily (``import oga.model`` compiles nothing).
"""

from __future__ import annotations

from oga._lazy import lazy_exports

# name -> module that defines it
_EXPORTS = {
    "Machine": "oga.model.machine",
    "load_machine": "oga.model.machine",
    "stable_range": "oga.model.stability",
    "contour_error": "oga.model.contour",
    "contour_metrics": "oga.model.metrics",
    "Plant": "oga.model.plant",
    "plant_of": "oga.model.plant",
}
_SUBMODULES = ("machine", "plant", "linear", "stability", "simulate", "response", "tangent",
               "kinematics", "contour", "metrics")

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS, _SUBMODULES)
