"""The fit report: one self-contained HTML page (figures inline as SVG, drawn with the
optimisation report's SVG panels; no plotting library).

Per fitted axis: the measured against the simulated following error and the residual
over time (the held-out part shaded), the fitted friction curve against the base
machine's, and the table of values with intervals; then the held-out check.
"""

from __future__ import annotations

import html

import numpy as np

from oga.defaults import IDENT_CONFIDENCE
from oga.identify.fit import PARAMETERS, axis_inputs
from oga.identify.workflow import Identification
from oga.report.optimize import _CSS, _Panel, _limits, _svg, _versions, decimate
from oga.model.simulate import axis_params, friction_command_m_s, simulate_axis

__all__ = ["identify_report"]

_MEAS, _SIM, _BASE, _RES = "#1f77b4", "#d62728", "#7f7f7f", "#2ca02c"


def _fig_axis(ident: Identification, a: str) -> str:
    tr, fit = ident.trace.axes[a], ident.fits[a]
    dt = ident.trace.dt_s
    cmd, ff, kp, kf = axis_inputs(tr, dt)
    p, _ = simulate_axis(axis_params(ident.machine, a), tr.act_m[0], cmd, ff, kp, kf)
    lag = fit.lag_samples
    n = p.size - lag
    t = np.arange(n) * dt
    fe_meas = (cmd[lag:] - tr.act_m[lag:]) * 1e6
    fe_sim = (cmd[lag:] - p[:n]) * 1e6
    res = (p[:n] - tr.act_m[lag:]) * 1e6
    idx = decimate(fe_meas)
    top = _Panel(80, 28, 960, 200, (t[0], t[-1]), _limits(fe_meas, fe_sim, include=[0.0]))
    top.line(t[idx], fe_meas[idx], _MEAS)
    idx_s = decimate(fe_sim)
    top.line(t[idx_s], fe_sim[idx_s], _SIM, dash="4,2")
    h = ident.holdout.get(a)
    bottom = _Panel(80, 290, 960, 140, (t[0], t[-1]), _limits(res, include=[0.0]))
    if h:
        for panel in (top, bottom):
            panel.vspan(t[-1] * (1 - h["fraction"]), t[-1], "#ff7f0e")
    top.legend([(f"axis {a}: measured", _MEAS), ("simulated (fitted model)", _SIM)])
    idx_r = decimate(res)
    bottom.line(t[idx_r], res[idx_r], _RES, width=1.0)
    bottom.legend([(f"residual, RMS {fit.residual_rms_m * 1e6:.3g} um", _RES)])
    return _svg(1100, 470, top.render("t (s)", "following error (um)")
                + bottom.render("t (s)", "simulated - measured (um)"), f"fit of axis {a}")


def _fig_friction(ident: Identification, base, a: str) -> str:
    vmax = base.axis(a).limits.vmax_m_s
    v = np.concatenate([-np.geomspace(vmax, 1e-5, 200), np.geomspace(1e-5, vmax, 200)])
    curves = []
    for m, colour, name in ((ident.machine, _SIM, "fitted"), (base, _BASE, f"base {base.name}")):
        params = axis_params(m, a)
        kv = m.axis(a).cascade.kv_n_s_m
        curves.append((np.array([friction_command_m_s(params, x) * kv for x in v]), colour, name))
    xs = np.sign(v) * np.log10(np.abs(v) / 1e-5)
    panel = _Panel(80, 28, 960, 220, (xs[0], xs[-1]), _limits(*(c for c, _, _ in curves)))
    for c, colour, _ in curves:
        panel.line(xs, c, colour)
    panel.legend([(f"axis {a}: {name}", colour) for _, colour, name in curves])
    return _svg(1100, 290, panel.render("sign(v) log10(|v| / 10 um/s)", "friction force (N)"),
                f"friction curve of axis {a}")


def _param_table(ident: Identification, base, a: str) -> str:
    fit = ident.fits[a]
    rows = []
    for k in PARAMETERS:
        b = getattr(base.axis(a).cascade, k)
        note = "" if (k != "mass_kg" or fit.mass_identified) else " (base: no force channel)"
        rows.append(f"<tr><th>{k}</th><td>{fit.values[k]:.6g}{note}</td><td>{fit.ci_low[k]:.6g}"
                    f"</td><td>{fit.ci_high[k]:.6g}</td><td>{b:.6g}</td></tr>")
    rows.append(f"<tr><th>dead_time_samples</th><td>{fit.dead_time_samples}</td><td></td><td></td>"
                f"<td>{base.dead_time_samples_of(a):g}</td></tr>")
    rows.append(f"<tr><th>logging lag (samples)</th><td>{fit.lag_samples}</td><td></td><td></td>"
                f"<td></td></tr>")
    cands = ", ".join(f"d={d:.4g} l={lg}: {rms * 1e6:.4g} um" for d, lg, rms in fit.candidates)
    pct = f"{IDENT_CONFIDENCE * 100:g} %"
    return (f'<table class="metrics"><tr><th>parameter</th><th>fitted</th><th>{pct} low</th>'
            f"<th>{pct} high</th><th>base</th></tr>{''.join(rows)}</table>"
            f"<p>Residual RMS {fit.residual_rms_m * 1e6:.4g} um, noise estimate "
            f"{fit.noise_rms_m * 1e6:.3g} um ({fit.noise_ratio:.3g} times), status "
            f"<b>{fit.status}</b>. Evidence of model error: the residual's correlation time "
            f"{fit.correlation_samples:.3g} samples (1: white), the model-error share "
            f"{fit.model_error_share:.3g} of the velocity loop's imprint on the positions"
            + (f", on a physical bound: {html.escape(', '.join(fit.at_bounds))}"
               if fit.at_bounds else "")
            + f"; dead time and lag tried (residual RMS): {html.escape(cands)}.</p>")


def identify_report(ident: Identification) -> str:
    """The report of an identification as one HTML page (str), the base machine beside the
    fitted values."""
    base = ident.base
    parts = [f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>oga identify: '
             f"{html.escape(ident.machine.name)}</title><style>{_CSS}</style></head><body>",
             f"<h1>oga identify: {html.escape(ident.machine.name)}</h1>",
             f"<p>Trace {html.escape(ident.trace.source)}: {ident.trace.n} samples at "
             f"{ident.trace.dt_s * 1e3:g} ms; status <b>{ident.status}</b>; "
             f"{ident.time_s:.1f} s of CPU.</p>"]
    n = 0
    for a in ident.fits:
        parts.append(f"<h2>Axis {a}</h2>")
        parts.append(_param_table(ident, base, a))
        n += 1
        parts.append(f'<figure id="fig{n}">{_fig_axis(ident, a)}<figcaption>Figure {n}. '
                     "Following error (command minus position) measured and simulated by the "
                     "fitted model from the same commands, and their difference; shaded: the "
                     "held-out part (predicted by a fit that did not see it).</figcaption></figure>")
        n += 1
        parts.append(f'<figure id="fig{n}">{_fig_friction(ident, base, a)}<figcaption>Figure {n}. '
                     "Friction force against velocity (Coulomb, Stribeck, viscous), fitted and "
                     "base; velocity on a signed log scale.</figcaption></figure>")
        h = ident.holdout.get(a)
        if h:
            parts.append(f"<p>Held-out check: a fit on the first {1 - h['fraction']:.0%} of the "
                         f"trace predicts the rest with residual RMS {h['rms_heldout_m'] * 1e6:.4g}"
                         f" um (on its own part {h['rms_fit_m'] * 1e6:.4g} um).</p>")
    parts += ["<h2>Machine file</h2>", f"<pre>{html.escape(ident.toml)}</pre>",
              "<h2>Versions</h2>",
              '<table class="meta">' + "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}"
                                              f"</td></tr>" for k, v in _versions()) + "</table>",
              "</body></html>"]
    return "\n".join(parts)
