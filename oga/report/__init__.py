"""Reports: self-contained HTML pages (inline SVG, no plotting library).

- :mod:`oga.report.optimize`: the report of an optimisation (``oga optimize --report``);
- :mod:`oga.report.compare`: the report of a controller comparison (``oga compare``).

The names below load lazily.
"""

from __future__ import annotations

from oga._lazy import lazy_exports

# name -> module that defines it
_EXPORTS = {
    "ReportData": "oga.report.optimize",
    "CertificateData": "oga.report.optimize",
    "report_data": "oga.report.optimize",
    "replay_report_data": "oga.report.optimize",
    "render_report": "oga.report.optimize",
    "decimate": "oga.report.optimize",
    "curvature": "oga.report.optimize",
    "render_compare_report": "oga.report.compare",
}
_SUBMODULES = ("optimize", "compare")

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS, _SUBMODULES)
