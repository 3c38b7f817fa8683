"""The comparison report: one self-contained HTML file (``oga compare --report``).

Pure: a :class:`oga.controllers.compare.Comparison` in, text out. One figure overlays the
contour error of every controller that ran (one line each, a legend naming them;
decimated keeping the peaks, :func:`oga.report.decimate`), then the table of the
figures and each controller's parameters and notes. The SVG drawing is the
optimisation report's (:mod:`oga.report.optimize`).
"""

from __future__ import annotations

import html

import numpy as np

from oga.controllers.compare import Comparison
from oga.defaults import REPORT_MAX_POINTS
from oga.report.optimize import _CSS, _cell, _flatten, _limits, _Panel, _svg, _table, _versions, decimate

__all__ = ["COLUMNS", "render_compare_report"]

#: One colour per controller, in the registry's order (colour-blind safe set, then grey).
_COLOURS = ("#d95f02", "#1b9e77", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d",
            "#666666")
_UM, _MM = 1e6, 1e3
#: Table columns: (header, row attribute or callable).
COLUMNS = (
    ("controller", "name"),
    ("status", "status"),
    ("needs firmware", "needs_firmware"),
    ("MSE CE (um^2)", "mse_ce_um2"),
    ("RMS CE (um)", "rms_ce_um"),
    ("max CE (um)", "max_ce_um"),
    ("max track x/y/z (um)", "track_max_um"),
    ("accel ratio", "accel_ratio"),
    ("jerk ratio", "jerk_ratio"),
    ("limits ok", "limits_ok"),
    ("time (s)", "time_s"),
)


def _value(row, attr):
    v = getattr(row, attr)
    if isinstance(v, dict):
        return "/".join(f"{x:.4g}" for x in v.values())
    if isinstance(v, float):
        return "" if not np.isfinite(v) else f"{v:.4g}"
    return _cell(v)


def _fig_ce(cmp: Comparison, max_points: int) -> str:
    sp = cmp.setpoints
    s = sp.s * _MM
    feed = sp.counted
    drawn = [(r, _COLOURS[i % len(_COLOURS)]) for i, r in enumerate(cmp.rows) if r.status != "failed"]
    series = [np.where(feed, r.ce_m * _UM, np.nan) for r, _ in drawn]
    panel = _Panel(80, 40, 960, 300, (s[0], s[-1]), _limits(*series, include=[0.0]))
    for (row, colour), ce in zip(drawn, series):
        idx = decimate(ce, max_points)
        panel.parts.append(f'<g class="controller" data-controller="{html.escape(row.name)}">')
        panel.line(s[idx], ce[idx], colour)
        panel.parts.append("</g>")
    panel.legend([(row.name, colour) for row, colour in drawn])
    return _svg(1100, 390, panel.render("s (mm)", "CE (um)"), "contour error of every controller")


def render_compare_report(cmp: Comparison, *, title: str | None = None,
                          max_points: int = REPORT_MAX_POINTS) -> str:
    """The comparison as one self-contained HTML page.

    Parameters
    ----------
    cmp : Comparison
        From :func:`oga.controllers.compare.compare`.
    title : str, optional
        Page title (default: the toolpath's name).
    max_points : int
        Decimation target per drawn line.

    Returns
    -------
    str
        HTML5 text; the figure inline as SVG, no external reference.
    """
    sp = cmp.setpoints
    title = title or f"oga compare: {sp.source}"
    head = (f"<p>Machine <b>{html.escape(cmp.machine)}</b>, {len(sp)} samples "
            f"({len(sp) * sp.dt:.3f} s at Te {sp.dt * 1e3:g} ms). Every controller runs on the "
            "same setpoints and plant; figures over the feed samples, command ratios of paper "
            "eq. 2 (1 = the axis limit).</p>")
    header = "".join(f"<th>{html.escape(h)}</th>" for h, _ in COLUMNS)
    body = "".join(
        f'<tr data-controller="{html.escape(r.name)}" class="status-{html.escape(r.status)}">'
        + "".join(f"<td>{html.escape(_value(r, attr))}</td>" for _, attr in COLUMNS) + "</tr>"
        for r in cmp.rows)
    table = f'<table class="compare"><tr>{header}</tr>{body}</table>'
    caption = ("Figure 1. Contour error of every controller that ran, against path length "
               "(feed samples; signed for a planar path: positive to the left of travel).")
    parts = [f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
             f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", head, table,
             f'<figure id="fig1">{_fig_ce(cmp, max_points)}<figcaption>{html.escape(caption)}'
             "</figcaption></figure>", "<h2>Controllers</h2>"]
    for r in cmp.rows:
        parts.append(f"<h3>{html.escape(r.name)}</h3>")
        if r.status == "failed":
            parts.append(f'<p class="status-failed">failed: {html.escape(r.message)}</p>')
            continue
        if r.status == "untuned":
            parts.append(f'<p class="status-failed">untuned, breaks the limits: '
                         f'{html.escape(r.message)}</p>')
        parts.append(_table(_flatten(r.parameters), "parameters"))
        if r.notes:
            parts.append("<ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in r.notes)
                         + "</ul>")
    parts += ["<h2>Versions</h2>", _table(_versions(), "meta"), "</body></html>"]
    return "\n".join(parts)
