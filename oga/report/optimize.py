"""The optimisation report: one self-contained HTML file, figures inline as SVG.

Pure: data in, text out (no files, no network, no plotting library; the SVG is
written here). The engine never imports this module.

Figures (x axis: path length s in mm unless stated):

1. the path (setpoints) with the baseline's and the optimised schedule's actual
   positions, the contour error magnified by a stated factor and drawn normal to
   the path, coloured by |CE|;
2. Kp and Kf per adjusted axis (schedule and baseline), with the path curvature
   ``kappa = |v x a| / |v|^3`` of the setpoints' velocity and acceleration (1/m);
3. the contour error of both replays, and the histograms of |CE| (feed samples);
4. per contouring axis, the velocity command's velocity, acceleration and jerk
   (paper eq. 2 differences of ``u``, the axis at rest before sample 0) against
   the axis limits;
5. per contouring axis, the following error ``pd - p`` against the machine's limit
   where it sets one;
6. per contouring axis, the phase and gain margins against Kp with the stable
   range, the criteria and the gains used;

and, for a table of the robust search (:mod:`oga.search.robust`), its certificate:

7. the distribution of the MSE ratio schedule / baseline over the plants of the
   uncertainty set (sorted, with its median, 90th percentile, worst and the bound 1);
8. the contour error of the schedule and of the baseline on the worst plant.

Long series are decimated (:func:`decimate`): per bucket the first, the smallest
and the largest sample survive, so peaks are kept.
"""

from __future__ import annotations

import html
import math
import platform
from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga.defaults import REPORT_MAX_POINTS
from oga.model.machine import Machine
from oga.verify.replay import Verification

__all__ = ["CertificateData", "ReportData", "curvature", "decimate", "render_report",
           "replay_report_data", "report_data"]

#: Colours of the |CE| scale, low to high (viridis-like).
_CE_COLOURS = ("#440154", "#472d7b", "#3b528b", "#2c728e", "#21918c", "#28ae80", "#5ec962",
               "#addc30", "#fde725")
#: Colours of the series: baseline, optimised/schedule, third (curvature, limits).
_BASE, _OPT, _GREY, _LIMIT = "#d95f02", "#1b9e77", "#888888", "#c00000"
_UM, _MM = 1e6, 1e3


@dataclass(frozen=True, eq=False)
class CertificateData:
    """What figures 7 and 8 draw of a robust table's certificate.

    Attributes
    ----------
    summary : dict
        The summary's ``certificate`` (:meth:`oga.verify.certificate.Certificate.summary`).
    ratio : ndarray, shape (P,)
        MSE ratio schedule / baseline per plant.
    schedule, baseline : Verification
        Replays of the certified schedule and of the baseline on the worst plant (the same
        object when the schedule is not at hand: a stored job whose table is the baseline).
    """

    summary: dict
    ratio: np.ndarray
    schedule: Verification
    baseline: Verification


@dataclass(frozen=True, eq=False)
class ReportData:
    """What the report draws.

    Attributes
    ----------
    setpoints : Setpoints
        The planned motion (N samples).
    machine : Machine
        The machine (limits, stability ranges).
    kp_m_min_per_mm, kf : ndarray, shape (N, 3)
        The exported gain schedule ((m/min)/mm, 1).
    baseline, optimized : Verification
        Replays of the fixed baseline gains and of the schedule.
    summary : dict
        The summary JSON (:meth:`oga.optimize.OptimizeResult.summary`).
    certificate : CertificateData or None
        The robust search's certificate; None for a nominal search (no figures 7, 8).
    """

    setpoints: Setpoints
    machine: Machine
    kp_m_min_per_mm: np.ndarray
    kf: np.ndarray
    baseline: Verification
    optimized: Verification
    summary: dict
    certificate: CertificateData | None = None


def report_data(job_or_result) -> ReportData:
    """ReportData of an :class:`oga.pipeline.Job` or an :class:`oga.optimize.OptimizeResult`."""
    if isinstance(job_or_result, ReportData):
        return job_or_result
    result = getattr(job_or_result, "result", job_or_result)
    summary = job_or_result.summary()
    cert = None
    if result.certificate is not None:
        worst = result.certificate.worst_plant
        cert = CertificateData(summary=summary["certificate"], ratio=result.certificate.ratio,
                               schedule=worst.schedule, baseline=worst.baseline)
    return ReportData(setpoints=result.setpoints, machine=result.machine,
                      kp_m_min_per_mm=result.schedule.kp_m_min_per_mm, kf=result.schedule.kf,
                      baseline=result.baseline, optimized=result.optimized, summary=summary,
                      certificate=cert)


def replay_report_data(setpoints: Setpoints, machine: Machine, kp_m_min_per_mm: np.ndarray,
                       kf: np.ndarray, summary: dict) -> ReportData:
    """ReportData of a stored job: its table's gains and the baseline replayed (no search).

    Parameters
    ----------
    setpoints : Setpoints
        The job's setpoints, planned again from its toolpath (N samples).
    machine : Machine
        The job's machine.
    kp_m_min_per_mm, kf : ndarray, shape (N, 3)
        The gains of its stored table.
    summary : dict
        Its stored summary (baseline gains, Kp bounds, setpoint hash).

    Raises
    ------
    PlanError
        The setpoints are not those the table was computed for.

    Notes
    -----
    A robust job's worst plant is drawn again from the machine's set (the summary's seed
    and counts) and the table's gains and the baseline replayed on it; where the table
    holds the baseline (the schedule was refused), the refused schedule is not stored and
    figure 8 shows the baseline alone.
    """
    from oga.errors import PlanError
    from oga.search.result import setpoints_digest
    from oga.verify.replay import verify

    if setpoints_digest(setpoints) != summary["setpoints_sha256"]:
        raise PlanError("report: the toolpath planned again gives other setpoints than the job's")
    n = len(setpoints)
    bounds = {a: tuple(b) for a, b in summary["kp_bounds_m_min_per_mm"].items()}
    base_kp = np.tile([summary["baseline"]["kp"][a] for a in AXES], (n, 1))
    base_kf = np.tile([summary["baseline"]["kf"][a] for a in AXES], (n, 1))
    cert = None
    sc = summary.get("certificate", {})
    if "ratio_per_plant" in sc:
        from oga.search.robust.plants import scenario_set
        from oga.model.stability import stable_range

        scen = scenario_set(machine, n=sc["monte_carlo"], seed=sc["seed"],
                            corners=sc["corners"] > 0)
        plant = scen.plants[scen.labels.index(sc["worst_plant"])]
        pb = {a: (float(r.kp_min), float(r.kp_max))
              for a, r in ((a, stable_range(plant, a)) for a in bounds)}
        base = verify(setpoints, plant, base_kp, base_kf, pb)
        cert = CertificateData(
            summary=sc, ratio=np.array(list(sc["ratio_per_plant"].values())),
            schedule=base if summary["kept_baseline"]
            else verify(setpoints, plant, kp_m_min_per_mm, kf, pb),
            baseline=base)
    return ReportData(setpoints=setpoints, machine=machine, kp_m_min_per_mm=kp_m_min_per_mm,
                      kf=kf, baseline=verify(setpoints, machine, base_kp, base_kf, bounds),
                      optimized=verify(setpoints, machine, kp_m_min_per_mm, kf, bounds),
                      summary=summary, certificate=cert)


# --- series helpers -----------------------------------------------------------------------------

def decimate(y: np.ndarray, max_points: int = REPORT_MAX_POINTS) -> np.ndarray:
    """Indices of the samples to draw of a long series, keeping its peaks.

    Parameters
    ----------
    y : ndarray, shape (N,)
        The series (NaN allowed).
    max_points : int
        About how many buckets to keep; each contributes its first, smallest and
        largest sample (at most 3 * max_points / 2 indices, plus the last sample).

    Returns
    -------
    ndarray of int, shape (M,)
        Sorted unique indices; all of them when ``N <= max_points``.
    """
    n = len(y)
    if n <= max_points:
        return np.arange(n)
    size = max(1, math.ceil(2 * n / max_points))
    starts = np.arange(0, n, size)
    yy = np.where(np.isnan(y), 0.0, y)
    pad = np.full(len(starts) * size, yy[-1])
    pad[:n] = yy
    blocks = pad.reshape(-1, size)
    lo = starts + blocks.argmin(axis=1)
    hi = starts + blocks.argmax(axis=1)
    idx = np.unique(np.concatenate([starts, lo, hi, [n - 1]]))
    return idx[idx < n]


def curvature(setpoints: Setpoints) -> np.ndarray:
    """Path curvature at each sample, ``|v x a| / |v|^3`` of the setpoints, 1/m.

    Returns
    -------
    ndarray, shape (N,)
        Curvature, 1/m; NaN where the path speed is below 1e-3 of its peak (undefined).
    """
    v, a = setpoints.vel, setpoints.acc
    speed = np.linalg.norm(v, axis=1)
    cross = np.linalg.norm(np.cross(v, a), axis=1)
    ok = speed > 1e-3 * max(speed.max(initial=0.0), 1e-300)
    out = np.full(len(speed), np.nan)
    out[ok] = cross[ok] / speed[ok] ** 3
    return out


def _command_derivatives(u: np.ndarray, te: float) -> tuple[np.ndarray, np.ndarray]:
    """Paper eq. 2 differences of ``u`` (N, 3): acceleration m/s^2 and jerk m/s^3 (rest before)."""
    u0 = np.vstack([np.zeros((2, u.shape[1])), u])
    d1 = np.diff(u0, axis=0)
    return d1[1:] / te, np.diff(d1, axis=0) / te**2


def _nice(x: float) -> float:
    """1, 2 or 5 times a power of ten, the nearest not above ``x`` (x > 0)."""
    e = math.floor(math.log10(x))
    m = x / 10**e
    return (5 if m >= 5 else 2 if m >= 2 else 1) * 10.0**e


def _ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    step = _nice((hi - lo) / n) if hi > lo else 1.0
    return np.arange(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1) * step


def _limits(*arrays, pad: float = 0.05, include=()) -> tuple[float, float]:
    vals = np.concatenate([np.ravel(a) for a in arrays] + [np.asarray(include, float)])
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return 0.0, 1.0
    lo, hi = float(vals.min()), float(vals.max())
    if hi - lo < 1e-12 * max(1.0, abs(hi)):
        span = max(abs(hi), 1.0) * 0.05
        return lo - span, hi + span
    d = (hi - lo) * pad
    return lo - d, hi + d


def _fmt(v: float) -> str:
    return f"{v:.4g}"


# --- SVG ------------------------------------------------------------------------------------------

class _Panel:
    """One plot area of a figure: data limits mapped onto a pixel box."""

    def __init__(self, x0, y0, w, h, xlim, ylim, *, equal=False):
        self.x0, self.y0, self.w, self.h = x0, y0, w, h
        self.xlim, self.ylim = xlim, ylim
        if equal:  # same scale on both axes, centred
            sx, sy = w / (xlim[1] - xlim[0]), h / (ylim[1] - ylim[0])
            s = min(sx, sy)
            cx, cy = sum(xlim) / 2, sum(ylim) / 2
            self.xlim = (cx - w / s / 2, cx + w / s / 2)
            self.ylim = (cy - h / s / 2, cy + h / s / 2)
        self.parts: list[str] = []

    def px(self, x):
        span = self.xlim[1] - self.xlim[0]
        return self.x0 + (np.asarray(x, float) - self.xlim[0]) / span * self.w

    def py(self, y):
        span = self.ylim[1] - self.ylim[0]
        return self.y0 + self.h - (np.asarray(y, float) - self.ylim[0]) / span * self.h

    def line(self, x, y, colour, *, width=1.2, dash=None, step=False):
        """A polyline (NaN breaks it; y clipped to the box); ``step``: a histogram outline."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        if step:
            x, y = np.repeat(x, 2)[1:-1], np.repeat(y, 2)
        d = _path_d(self.px(x), self.py(np.clip(y, *self.ylim)))
        if d:
            extra = f' stroke-dasharray="{dash}"' if dash else ""
            self.parts.append(f'<path d="{d}" fill="none" stroke="{colour}" '
                              f'stroke-width="{width}"{extra}/>')

    def hline(self, y, colour, *, dash="5,3", label=""):
        if self.ylim[0] <= y <= self.ylim[1]:
            self.line(self.xlim, [y, y], colour, width=1, dash=dash)
            if label:
                self.text(self.x0 + self.w - 4, float(self.py(y)) - 3, label, colour, anchor="end")

    def vline(self, x, colour, *, dash="5,3", width=1.5):
        if self.xlim[0] <= x <= self.xlim[1]:
            self.line([x, x], self.ylim, colour, width=width, dash=dash)

    def vspan(self, lo, hi, colour, opacity=0.15):
        a, b = float(self.px(max(lo, self.xlim[0]))), float(self.px(min(hi, self.xlim[1])))
        if b > a:
            self.parts.append(f'<rect x="{a:.1f}" y="{self.y0}" width="{b - a:.1f}" '
                              f'height="{self.h}" fill="{colour}" fill-opacity="{opacity}"/>')

    def text(self, x, y, s, colour="#222", *, anchor="start", size=11):
        self.parts.append(f'<text x="{x:.1f}" y="{y:.1f}" fill="{colour}" font-size="{size}" '
                          f'text-anchor="{anchor}">{html.escape(s)}</text>')

    def legend(self, items):
        """``items``: (label, colour) written just above the box, from its left."""
        x = self.x0
        for label, colour in items:
            self.parts.append(f'<rect x="{x:.1f}" y="{self.y0 - 10}" width="12" height="3" '
                              f'fill="{colour}"/>')
            self.text(x + 15, self.y0 - 4, label, colour)
            x += 22 + 6.5 * len(label)

    def render(self, xlabel, ylabel) -> str:
        """Frame, ticks, grid and labels around what was drawn."""
        out = [f'<rect x="{self.x0}" y="{self.y0}" width="{self.w}" height="{self.h}" '
               f'fill="#fff" stroke="#444"/>']
        for t in _ticks(*self.xlim):
            x = float(self.px(t))
            out.append(f'<line x1="{x:.1f}" y1="{self.y0}" x2="{x:.1f}" y2="{self.y0 + self.h}" '
                       f'stroke="#eee"/><text x="{x:.1f}" y="{self.y0 + self.h + 13}" '
                       f'font-size="10" text-anchor="middle">{_fmt(t)}</text>')
        for t in _ticks(*self.ylim):
            y = float(self.py(t))
            out.append(f'<line x1="{self.x0}" y1="{y:.1f}" x2="{self.x0 + self.w}" y2="{y:.1f}" '
                       f'stroke="#eee"/><text x="{self.x0 - 4}" y="{y + 3:.1f}" font-size="10" '
                       f'text-anchor="end">{_fmt(t)}</text>')
        out += self.parts
        out.append(f'<text x="{self.x0 + self.w / 2:.1f}" y="{self.y0 + self.h + 27}" '
                   f'font-size="11" text-anchor="middle">{html.escape(xlabel)}</text>')
        yc = self.y0 + self.h / 2
        out.append(f'<text x="{self.x0 - 46}" y="{yc:.1f}" font-size="11" text-anchor="middle" '
                   f'transform="rotate(-90 {self.x0 - 46} {yc:.1f})">{html.escape(ylabel)}</text>')
        return "".join(out)


def _path_d(px: np.ndarray, py: np.ndarray) -> str:
    """SVG path data through the points; a NaN starts a new sub-path."""
    out, pen = [], "M"
    for x, y in zip(px.tolist(), py.tolist()):
        if math.isnan(x) or math.isnan(y):
            pen = "M"
            continue
        out.append(f"{pen}{x:.1f} {y:.1f}")
        pen = "L"
    return "".join(out)


def _svg(width: int, height: int, body: str, label: str) -> str:
    return (f'<svg width="{width}" height="{height}" '
            f'viewBox="0 0 {width} {height}" role="img" aria-label="{html.escape(label)}" '
            f'font-family="sans-serif">{body}</svg>')


# --- figures --------------------------------------------------------------------------------------

def _plane_axes(sp: Setpoints) -> tuple[int, int]:
    """Column indices (horizontal, vertical) of the drawing plane."""
    named = {"xy": (0, 1), "zx": (0, 2), "yz": (1, 2)}
    if sp.plane in named:
        return named[sp.plane]
    spans = np.ptp(sp.pos, axis=0)
    i, j = sorted(np.argsort(spans)[-2:])
    return int(i), int(j)


def _ce_drawn(sp: Setpoints, v: Verification, i: int, j: int, factor: float) -> np.ndarray:
    """Points drawn for a replay: setpoint + factor * |CE| along the in-plane normal
    toward the actual position, shape (N, 2), m."""
    p = sp.pos[:, [i, j]]
    t = sp.vel[:, [i, j]]
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    e = v.pos[:, [i, j]] - p
    e_perp = e - np.sum(e * t, axis=1, keepdims=True) * t
    norm = np.linalg.norm(e_perp, axis=1, keepdims=True)
    n_hat = np.where(norm > 0, e_perp / np.maximum(norm, 1e-300), 0.0)
    return p + factor * np.abs(v.ce)[:, None] * n_hat


def _magnification(sp: Setpoints, ce_max_m: float, i: int, j: int) -> float:
    """A round factor making the largest |CE| about 4 % of the path's extent."""
    extent = float(max(np.ptp(sp.pos[:, i]), np.ptp(sp.pos[:, j])))
    if ce_max_m <= 0 or extent <= 0:
        return 1.0
    return max(1.0, _nice(0.04 * extent / ce_max_m))


def _fig_path(d: ReportData, max_points: int) -> tuple[str, str]:
    sp = d.setpoints
    i, j = _plane_axes(sp)
    feed = sp.counted
    ce_max = max(float(np.abs(v.ce[feed]).max(initial=0.0)) for v in (d.baseline, d.optimized))
    factor = _magnification(sp, ce_max, i, j)
    drawn = [_ce_drawn(sp, v, i, j, factor) for v in (d.baseline, d.optimized)]
    xlim = _limits(sp.pos[:, i] * _MM, *(p[:, 0] * _MM for p in drawn))
    ylim = _limits(sp.pos[:, j] * _MM, *(p[:, 1] * _MM for p in drawn))
    pw = 960  # panels stacked, each as tall as the path's aspect asks (within 160..480 px)
    ph = int(np.clip(pw * (ylim[1] - ylim[0]) / (xlim[1] - xlim[0]), 160, 480))
    body, y = [], 28
    for v, p, name in zip((d.baseline, d.optimized), drawn, ("baseline", "optimised")):
        panel = _Panel(80, y, pw, ph, xlim, ylim, equal=True)
        keep = np.union1d(decimate(sp.pos[:, i], max_points), decimate(sp.pos[:, j], max_points))
        panel.line(sp.pos[keep, i] * _MM, sp.pos[keep, j] * _MM, _GREY, width=0.8, dash="3,2")
        ce = np.where(feed, np.abs(v.ce), np.nan)
        idx = decimate(ce, max_points)
        level = np.minimum(ce[idx] / max(ce_max, 1e-300) * len(_CE_COLOURS),
                           len(_CE_COLOURS) - 1)
        px, py = panel.px(p[idx, 0] * _MM), panel.py(p[idx, 1] * _MM)
        for c, colour in enumerate(_CE_COLOURS):  # one path per colour level
            seg = [f"M{px[m]:.1f} {py[m]:.1f}L{px[m + 1]:.1f} {py[m + 1]:.1f}"
                   for m in range(len(idx) - 1) if c <= level[m] < c + 1]
            if seg:
                panel.parts.append(f'<path d="{"".join(seg)}" fill="none" stroke="{colour}" '
                                   f'stroke-width="2" stroke-linecap="round"/>')
        panel.text(panel.x0 + 6, panel.y0 + 14,
                   f"{name}: max |CE| {v.metrics.max_abs_m * _UM:.3g} um")
        body.append(panel.render(f"{AXES[i]} (mm)", f"{AXES[j]} (mm)"))
        y += ph + 45
    n = len(_CE_COLOURS)  # colour bar
    for c, colour in enumerate(_CE_COLOURS):
        body.append(f'<rect x="{300 + c * 50}" y="{y}" width="50" height="10" fill="{colour}"/>')
    for c in range(n + 1):
        body.append(f'<text x="{300 + c * 50}" y="{y + 24}" font-size="10" '
                    f'text-anchor="middle">{ce_max * _UM * c / n:.3g}</text>')
    body.append(f'<text x="290" y="{y + 9}" font-size="11" text-anchor="end">|CE| (um)</text>')
    caption = (f"Path in the {AXES[i]}{AXES[j]} plane: setpoints (grey, dashed) and the actual "
               f"positions of each replay with the contour error magnified {factor:g}x "
               f"(drawn at setpoint + {factor:g} x |CE| along the normal toward the actual "
               f"position), coloured by |CE| on one scale for both.")
    return _svg(1100, y + 35, "".join(body), "path"), caption


def _fig_gains(d: ReportData, max_points: int) -> tuple[str, str]:
    sp = d.setpoints
    s = sp.s * _MM
    adjusted = d.summary["adjusted"]
    kappa = curvature(sp)
    rows = [("Kp ((m/min)/mm)", d.kp_m_min_per_mm, "kp"), ("Kf", d.kf, "kf")]
    w, ph = 1100, 150
    body, y = [], 28
    colours = {"x": "#1b9e77", "y": "#7570b3", "z": "#e7298a"}
    for label, gains, key in rows:
        cols = [AXES.index(a) for a in adjusted]
        base = [d.summary["baseline"][key][a] for a in adjusted]
        panel = _Panel(80, y, 960, ph, (s[0], s[-1]), _limits(gains[:, cols], include=base))
        for a, c, b in zip(adjusted, cols, base):
            panel.hline(b, _BASE)
            idx = decimate(gains[:, c], max_points)
            panel.line(s[idx], gains[idx, c], colours[a], width=1.5)
        panel.legend([(f"{key.capitalize()} {a}", colours[a]) for a in adjusted]
                     + [("baseline", _BASE)])
        body.append(panel.render("s (mm)", label))
        y += ph + 60
    idx = decimate(kappa, max_points)
    panel = _Panel(80, y, 960, ph, (s[0], s[-1]), _limits(kappa, include=[0.0]))
    panel.line(s[idx], kappa[idx], "#333", width=1.2)
    body.append(panel.render("s (mm)", "curvature (1/m)"))
    caption = ("Gains of the exported schedule per adjusted axis against path length (baseline "
               "dashed), and the path curvature |v x a| / |v|^3 of the setpoints (1/m; not "
               "drawn at standstill).")
    return _svg(w, y + ph + 40, "".join(body), "gains"), caption


def _ce_panel(sp: Setpoints, series, max_points: int) -> str:
    """The contour error of replays ``series`` ((ce_um, colour, label), ...) against path
    length, feed samples only."""
    s = sp.s * _MM
    feed = sp.counted
    panel = _Panel(80, 28, 960, 200, (s[0], s[-1]),
                   _limits(*(np.where(feed, c, np.nan) for c, _, _ in series), include=[0.0]))
    for ce, colour, _ in series:
        ce = np.where(feed, ce, np.nan)
        idx = decimate(ce, max_points)
        panel.line(s[idx], ce[idx], colour)
    panel.legend([(name, colour) for _, colour, name in series])
    return panel.render("s (mm)", "CE (um)")


def _fig_ce(d: ReportData, max_points: int) -> tuple[str, str]:
    sp = d.setpoints
    feed = sp.counted
    series = [(v.ce * _UM, colour, name) for v, colour, name in
              ((d.baseline, _BASE, "baseline"), (d.optimized, _OPT, "optimised"))]
    body = [_ce_panel(sp, series, max_points)]
    mags = [np.abs(c[feed]) for c, _, _ in series]
    top = max(float(m.max(initial=0.0)) for m in mags) or 1.0
    edges = np.linspace(0.0, top, 41)
    counts = [np.log10(1.0 + np.histogram(m, bins=edges)[0]) for m in mags]
    c_top = max(float(c.max()) for c in counts) * 1.08 or 1.0
    hist = _Panel(80, 300, 960, 180, (0.0, top), (0.0, c_top))
    for c, (_, colour, _) in zip(counts, series):
        hist.line(edges, c, colour, width=1.5, step=True)
    hist.legend([(f"{name}: rms {d_.metrics.rms_m * _UM:.3g} um", colour) for
                 (_, colour, name), d_ in zip(series, (d.baseline, d.optimized))])
    body.append(hist.render("|CE| (um)", "log10(1 + samples)"))
    caption = ("Contour error of both replays against path length (feed samples; signed for a "
               "planar path: positive to the left of travel), and the histograms of |CE| "
               "(40 equal bins, counts on a log scale).")
    return _svg(1100, 520, "".join(body), "contour error"), caption


def _replays_panel(y, s, vals, limit: float, axis: str, ylabel: str, max_points: int,
                   rapids) -> str:
    """One panel of a per-axis figure at height ``y``: the baseline's and the schedule's
    series ``vals`` against path length ``s`` (mm), ``+-limit`` in red (``inf``: none), and
    the rapids' spans ``(s0, s1)`` (mm) shaded."""
    limited = math.isfinite(limit)
    panel = _Panel(80, y, 960, 110, (s[0], s[-1]),
                   _limits(*vals, include=[-limit, limit] if limited else []))
    for lo, hi in rapids:
        panel.vspan(lo, hi, _GREY, opacity=0.2)
    for colour, val in zip((_BASE, _OPT), vals):
        idx = decimate(val, max_points)
        panel.line(s[idx], val[idx], colour, width=1.0)
    if limited:
        panel.hline(limit, _LIMIT, label="limit")
        panel.hline(-limit, _LIMIT)
    panel.legend([(f"axis {axis}", "#222"), ("baseline", _BASE), ("optimised", _OPT)]
                 + ([("rapid", _GREY)] if rapids else []))
    return panel.render("s (mm)", ylabel)


def _replays_figure(d: ReportData, rows, title: str, max_points: int) -> str:
    """A figure of :func:`_replays_panel` panels stacked top to bottom, one per row
    ``(axis, vals, limit, ylabel)``."""
    s = d.setpoints.s * _MM
    edges = np.flatnonzero(np.diff(np.concatenate([[0], d.setpoints.rapid.astype(np.int8), [0]])))
    rapids = [(s[a], s[b - 1]) for a, b in zip(edges[::2], edges[1::2])]  # runs [a, b)
    body = [_replays_panel(28 + r * (110 + 58), s, vals, limit, a, ylabel, max_points, rapids)
            for r, (a, vals, limit, ylabel) in enumerate(rows)]
    return _svg(1100, 28 + len(rows) * (110 + 58) + 10, "".join(body), title)


def _fig_commands(d: ReportData, max_points: int) -> tuple[str, str]:
    sp = d.setpoints
    lim = d.machine.axis_limits()
    derivs = [(v.u, *_command_derivatives(v.u, sp.dt)) for v in (d.baseline, d.optimized)]
    units = (("velocity (m/s)", lim.vmax_m_s), ("acceleration (m/s^2)", lim.amax_m_s2),
             ("jerk (m/s^3)", lim.jmax_m_s3))
    rows = [(AXES[k], [der[q][:, k] for der in derivs], float(limit[k]), label)
            for k in sp.moving_axes for q, (label, limit) in enumerate(units)]
    caption = ("Per contouring axis, the velocity command u of each replay and its acceleration "
               "and jerk as paper eq. 2 computes them (first and second differences over Te, the "
               "axis at rest before the start), against the axis limits (red). Eq. 2 is checked "
               "at every sample, rapids (shaded), dwells, the start and the end included.")
    return _replays_figure(d, rows, "velocity command", max_points), caption


def _fig_following(d: ReportData, max_points: int) -> tuple[str, str]:
    sp = d.setpoints
    limit = d.machine.ferror_limits() * _MM
    rows = [(AXES[k], [(sp.pos[:, k] - v.pos[:, k]) * _MM for v in (d.baseline, d.optimized)],
             float(limit[k]), "following error (mm)") for k in sp.moving_axes]
    caption = ("Per contouring axis, the following error pd - p of each replay, against the "
               "machine's limit (red) where its file sets one (ferror_max_m, checked at every "
               "sample, rapids (shaded) included). On straight moves the schedule may let an axis lag "
               "along the path, which costs no contour error.")
    return _replays_figure(d, rows, "following error", max_points), caption


def _fig_stability(d: ReportData) -> tuple[str, str]:
    from oga.model.stability import stable_range

    sp = d.setpoints
    moving = [AXES[k] for k in sp.moving_axes]
    bounds = d.summary["kp_bounds_m_min_per_mm"]
    body, y = [], 28
    for a in moving:
        k = AXES.index(a)
        rng = stable_range(d.machine, a)
        used = d.kp_m_min_per_mm[:, k]
        base = d.summary["baseline"]["kp"][a]
        xlim = _limits(rng.kp, pad=0.02)
        for q, (vals, crit, label) in enumerate(
                ((rng.pm_deg, rng.pm_min_deg, "phase margin (deg)"),
                 (rng.gm_db, rng.gm_min_db, "gain margin (dB)"))):
            panel = _Panel(80 + q * 520, y, 440, 170, xlim, _limits(vals, include=[crit, 0.0]))
            panel.vspan(rng.kp_min, rng.kp_max, "#2c7fb8")
            panel.vspan(*bounds[a], "#2c7fb8", opacity=0.15)
            panel.vspan(float(used.min()), float(used.max()), _OPT, opacity=0.45)
            panel.vline(float(used.min()), _OPT, dash=None)
            panel.vline(float(used.max()), _OPT, dash=None)
            panel.line(rng.kp, vals, "#222", width=1.5)
            panel.hline(crit, _LIMIT, label=f"criterion {crit:g}")
            panel.vline(base, _BASE)
            panel.legend([(f"axis {a}", "#222"), ("baseline Kp", _BASE),
                          ("Kp used", _OPT), ("stable / allowed", "#2c7fb8")])
            body.append(panel.render("Kp ((m/min)/mm)", label))
        y += 170 + 60
    caption = ("Per contouring axis, the phase and gain margins of the position loop against Kp; "
               "the stable range (light blue, darker where the allowed Kp bounds overlap it), "
               "the margin criteria (red), the baseline Kp (dashed) and the span of Kp the "
               "schedule uses (green).")
    return _svg(1100, y + 10, "".join(body), "stability"), caption


def _fig_ratio(c: CertificateData) -> tuple[str, str]:
    from oga.verify.certificate import confidence_text

    sc = c.summary
    ratio = np.sort(c.ratio)
    frac = np.arange(1, len(ratio) + 1) / len(ratio)
    panel = _Panel(80, 28, 960, 220, _limits(ratio, include=[0.0, 1.0], pad=0.03),
                   (0.0, 1.02))
    panel.line(np.concatenate([[ratio[0]], ratio]), np.concatenate([[0.0], frac]), _OPT,
               width=1.5, step=True)
    for key, label, colour in (("ratio_median", "median", _GREY), ("ratio_p90", "p90", _GREY),
                               ("ratio_worst", "worst", _BASE)):
        panel.vline(sc[key], colour)
        panel.text(float(panel.px(sc[key])) + 3, 44 if key != "ratio_p90" else 58,
                   f"{label} {sc[key]:.3f}", colour)
    panel.vline(1.0, _LIMIT, dash=None)
    panel.text(float(panel.px(1.0)) - 3, 240, "bound 1", _LIMIT, anchor="end")
    panel.legend([(f"{sc['plants']} plants ({sc['monte_carlo']} Monte Carlo, seed "
                   f"{sc['seed']}; {sc['corners']} corners)", _OPT)])
    body = panel.render("MSE(CE) ratio schedule / baseline on the same plant",
                        "share of plants")
    caption = (f"Certificate {sc['status']}: the MSE(CE) ratio of the schedule to the fixed "
               "baseline on each plant of the machine's uncertainty set, sorted (the share of "
               "plants at or below each ratio), with the median, 90th percentile and worst, "
               "and the bound 1 (a worse table is not exported). Plants where a limit breaks: "
               f"schedule {len(sc['breaks']['schedule'])}, baseline "
               f"{len(sc['breaks']['baseline'])}, schedule only "
               f"{len(sc['breaks']['schedule-only'])}."
               + (f" Confidence: {confidence_text(sc)}." if "confidence" in sc
                  else ""))
    return _svg(1100, 300, body, "certificate ratio"), caption


def _fig_worst_plant(d: ReportData, max_points: int) -> tuple[str, str]:
    c = d.certificate
    replays = ((c.baseline, _BASE, "baseline"),) + (
        () if c.schedule is c.baseline else ((c.schedule, _OPT, "schedule"),))
    series = [(v.ce * _UM, colour, f"{name}: rms {v.metrics.rms_m * _UM:.3g} um, max "
               f"{v.metrics.max_abs_m * _UM:.3g} um") for v, colour, name in replays]
    caption = (f"Contour error on the worst plant of the certificate, {c.summary['worst_plant']} "
               f"(MSE ratio {c.summary['ratio_worst']:.3f}): the schedule and the fixed baseline "
               "replayed on it (feed samples; signed for a planar path)."
               + (" The refused schedule is not stored with the job: the baseline alone."
                  if c.schedule is c.baseline else ""))
    return _svg(1100, 280, _ce_panel(d.setpoints, series, max_points), "worst plant"), caption


# --- tables and page ------------------------------------------------------------------------------

def _flatten(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    out = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out += _flatten(v, key + ".")
        else:
            out.append((key, v))
    return out


def _cell(v) -> str:
    if isinstance(v, bool) or v is None:
        return str(v).lower() if isinstance(v, bool) else "null"
    if isinstance(v, float):
        return f"{v:.7g}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_cell(x) for x in v) if v else "none"
    return str(v)


def _table(rows: list[tuple[str, object]], cls: str) -> str:
    body = "".join(f'<tr data-key="{html.escape(k)}"><th>{html.escape(k)}</th>'
                   f"<td>{html.escape(_cell(v))}</td></tr>" for k, v in rows)
    return f'<table class="{cls}">{body}</table>'


def _versions() -> list[tuple[str, str]]:
    import numba

    import oga

    return [("oga", oga.__version__), ("numpy", np.__version__), ("numba", numba.__version__),
            ("python", platform.python_version())]


_CSS = """
body{font-family:sans-serif;max-width:1140px;margin:1em auto;color:#222}
figure{margin:1.5em 0}figcaption{font-size:.9em;color:#444;max-width:1000px}
table{border-collapse:collapse;font-size:.85em;margin:.5em 0}
th,td{border:1px solid #ccc;padding:2px 8px;text-align:left}th{font-weight:normal;color:#555}
td{font-family:monospace}.status-ok{color:#1b7f3b}.status-failed{color:#c00000}
"""


def render_report(job_or_result, *, title: str | None = None,
                  max_points: int = REPORT_MAX_POINTS) -> str:
    """The report of a job as one self-contained HTML page.

    Parameters
    ----------
    job_or_result : Job, OptimizeResult or ReportData
        What to report on.
    title : str, optional
        Page title (default: the toolpath's name).
    max_points : int
        Decimation target per drawn line (:func:`decimate`).

    Returns
    -------
    str
        HTML5 text; figures inline as SVG, no external reference.
    """
    d = report_data(job_or_result)
    sm = d.summary
    title = title or f"oga report: {sm['toolpath']}"
    figures = [_fig_path(d, max_points), _fig_gains(d, max_points), _fig_ce(d, max_points),
               _fig_commands(d, max_points), _fig_following(d, max_points), _fig_stability(d)]
    if d.certificate is not None:
        figures += [_fig_ratio(d.certificate), _fig_worst_plant(d, max_points)]
    status = sm["status"]
    head = (f"<p>Machine <b>{html.escape(sm['machine'])}</b>, {sm['samples']} samples "
            f"({sm['duration_s']:.3f} s), contouring axes {', '.join(sm['contouring_axes'])}, "
            f"adjusted {', '.join(sm['adjusted'])} ({', '.join(sm['gains'])}). Status "
            f'<b class="status-{html.escape(status)}">{html.escape(status)}</b>; MSE(CE) ratio '
            f"{_cell(sm['ratio_mse'])}"
            + (f"; the searched schedule was not kept "
               f"({html.escape(sm.get('kept_baseline_reason', ''))}), the table holds the "
               "baseline gains" if sm["kept_baseline"] else "") + ".</p>")
    metric_rows = []
    for key in ("mse_ce_um2", "rms_ce_um", "max_ce_um", "p95_ce_um"):
        metric_rows.append((key, sm["baseline"][key], sm["optimized"][key]))
    for a in sm["contouring_axes"]:  # the largest following error (the limit: in the summary)
        metric_rows.append((f"track_max_um.{a}", sm["baseline"]["track_max_um"][a],
                            sm["optimized"]["track_max_um"][a]))
    metrics = ('<table class="metrics"><tr><th>metric</th><th>baseline</th><th>optimised</th>'
               "</tr>" + "".join(f'<tr data-key="{k}"><th>{k}</th><td>{_cell(b)}</td>'
                                 f"<td>{_cell(o)}</td></tr>" for k, b, o in metric_rows)
               + "</table>")
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", head, "<h2>Contour error</h2>", metrics]
    for n, (svg, caption) in enumerate(figures, 1):
        parts.append(f'<figure id="fig{n}">{svg}<figcaption>Figure {n}. '
                     f"{html.escape(caption)}</figcaption></figure>")
    hashes = [("toolpath_sha256", sm["toolpath_sha256"]), ("setpoints_sha256",
              sm["setpoints_sha256"]), ("machine_sha256", sm["machine_sha256"])]
    parts += ["<h2>Hashes and versions</h2>", _table(hashes + _versions(), "meta"),
              "<h2>Summary and options</h2>",
              _table([r for r in _flatten(sm)
                      if not r[0].startswith("certificate.ratio_per_plant.")], "summary"),
              "</body></html>"]
    return "\n".join(parts)
