"""Verification: a schedule replayed from scratch, on the machine and on its uncertainty set.

- :mod:`oga.verify.replay`: the replay on the nominal machine (:func:`verify`): every
  sample's limits, following error and contour error;
- :mod:`oga.verify.certificate`: a table and the fixed baseline replayed on every plant of
  the uncertainty set (:func:`certify`).

The names below load lazily.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

# name -> module that defines it
_EXPORTS = {
    "verify": "oga.verify.replay",
    "Verification": "oga.verify.replay",
    "command_ratios": "oga.verify.replay",
    "ferror_ratios": "oga.verify.replay",
    "certify": "oga.verify.certificate",
    "certify_result": "oga.verify.certificate",
    "Certificate": "oga.verify.certificate",
}
_SUBMODULES = ("replay", "certificate")

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS, _SUBMODULES)
