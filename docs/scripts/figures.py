"""The figures of the README and the docs, drawn by oga's own report code, as PNG files.

Run from the repository root: ``python docs/scripts/figures.py [NAME ...]`` (default: all)
writes ``docs/figures/NAME.png`` and prints, per figure, the date, the host and the figures it
shows (the pages quote them). Each figure is an SVG of :mod:`oga.report.optimize` (or of the
identification report, :mod:`oga.identify.report`, drawn with the same panels), rasterised by
headless Chromium (Debian's ``chromium``, driven by Playwright, both of the dev setup;
``OGA_CHROMIUM`` names another binary). The figures:

- ``contour-error``: the README's figure. The contour error of the best fixed gains and of
  the table on a real program (``tests/data/cncjs_toolpath.nc``, cncjs's visualizer fixture,
  MIT), the default (robust) ``oga optimize`` on ``ucp710``, and the table's gains
  (report figures 3 and 2);
- ``certificate``: the certificate of the Quickstart's table (``reference_xz``): the sorted
  MSE ratios over the 96 plants, and the contour error on the worst plant (figures 7, 8);
- ``identification-fit``: ``oga identify`` on a trace recorded on a simulated machine that is
  not the base (ucp710 with mass -20 %, friction and viscous -50 %, Kv +20 %, Tn -30 %): the
  following error measured and simulated by the fitted model, and the residual;
- ``cycle-time``: the planned cycle time of every program of ``bench/bench_plan.py`` that is
  at hand (``--shared DIR``: LinuxCNC's programs under ``DIR/toolpaths/external``) over toppra's time-optimal bound along the same blocks (the bench's own
  :func:`measure`), drawn with the report's panels.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "docs" / "figures"
#: The shared folder holding ``toolpaths/external`` (LinuxCNC's GPL programs, never copied
#: into the repository): ``--shared``, default ``../shared`` beside the checkout.
SHARED = ROOT.parent / "shared"
CHROMIUM = os.environ.get("OGA_CHROMIUM", "/usr/bin/chromium")
CNCJS = ROOT / "tests" / "data" / "cncjs_toolpath.nc"
REFERENCE = ROOT / "examples" / "data" / "reference_xz.ngc"


def _job(path: Path, options: dict | None = None):
    from feedplan.read import read_file
    from oga.model.machine import load_machine
    from oga.options import OptimizeOptions
    from oga.pipeline import run_job

    text, fmt = read_file(str(path))
    return run_job(text, fmt, load_machine("ucp710"), OptimizeOptions.model_validate(options or {}),
                   source=path.name)


def contour_error() -> tuple[list[str], str]:
    """README figure: CE of fixed gains and of the table on cncjs_toolpath, and the gains."""
    from oga.report.optimize import _BASE, _OPT, _UM, _ce_panel, _fig_gains, _svg, report_data

    job = _job(CNCJS)
    d = report_data(job)
    series = [(v.ce * _UM, colour, f"{name}: rms {v.metrics.rms_m * _UM:.3g} um, max "
               f"{v.metrics.max_abs_m * _UM:.3g} um")
              for v, colour, name in ((d.baseline, _BASE, "best fixed gains"),
                                      (d.optimized, _OPT, "oga table"))]
    gains = _clip(_fig_gains(d, 1500)[0], 420)  # Kp and Kf (not the curvature panel)
    sm = d.summary
    note = (f"cncjs_toolpath on ucp710: MSE ratio {sm['ratio_mse']:.3f}, certificate "
            f"median {sm['certificate']['ratio_median']:.3f} / p90 "
            f"{sm['certificate']['ratio_p90']:.3f} / worst {sm['certificate']['ratio_worst']:.3f}"
            f"; baseline Kp {sm['baseline']['kp']['x']}, Kf {sm['baseline']['kf']['x']}")
    return [_svg(1100, 270, _ce_panel(d.setpoints, series, 1500), "contour error"), gains], note


def _clip(svg: str, height: int) -> str:
    """The top ``height`` pixels of an SVG."""
    return f'<div style="height:{height}px;overflow:hidden">{svg}</div>'


def certificate() -> tuple[list[str], str]:
    """The certificate of the Quickstart's table: ratio distribution and worst plant."""
    from oga.report.optimize import _fig_ratio, _fig_worst_plant, report_data

    d = report_data(_job(REFERENCE))
    c = d.summary["certificate"]
    note = (f"reference_xz on ucp710: median {c['ratio_median']:.3f}, p90 {c['ratio_p90']:.3f}, "
            f"worst {c['ratio_worst']:.3f} ({c['worst_plant']})")
    return [_fig_ratio(d.certificate)[0], _fig_worst_plant(d, 1500)[0]], note


def identification_fit() -> tuple[list[str], str]:
    """oga identify on a simulated machine's trace: following error, fit and residual."""
    from feedplan.read import read_toolpath
    from oga.identify.excite import excite_program
    from oga.identify.report import _fig_axis, _fig_friction
    from oga.identify.sim import synthetic_trace
    from oga.identify.trace import read_trace, trace_csv
    from oga.identify.workflow import identify
    from oga.model.machine import load_machine
    from oga.pipeline import plan_toolpath

    base = load_machine("ucp710")
    c = base.axis("x").cascade
    true = base.model_copy(update={"axes": {**base.axes, "x": base.axis("x").model_copy(
        update={"cascade": c.model_copy(update=dict(
            mass_kg=c.mass_kg * 0.8, coulomb_n=c.coulomb_n * 0.5, static_n=c.static_n * 0.5,
            viscous_n_s_m=c.viscous_n_s_m * 0.5, kv_n_s_m=c.kv_n_s_m * 1.2,
            tn_s=c.tn_s * 0.7))})}})
    sp = plan_toolpath(read_toolpath(excite_program(base, ["x"], travel_mm=50.0), "gcode"),
                       base, feed_m_s=None, tol_m=2e-5)
    ch = synthetic_trace(sp, true, ["x"], 3.0, 0.8, noise_m=1e-7, quantum_m=1e-7, seed=1)
    t = ch.pop("t_s")
    trace = read_trace(trace_csv(t, ch), "csv", kp=3.0, kf=0.8)
    ident = identify(trace, base, axes=["x"], holdout_fraction=0.25)
    fit = ident.fits["x"]
    note = (f"x: Kv {fit.values['kv_n_s_m']:.4g} N s/m (true at the base mass "
            f"{c.kv_n_s_m * 1.2 / 0.8:.4g}), Tn {fit.values['tn_s'] * 1e3:.3g} ms (true "
            f"{c.tn_s * 0.7 * 1e3:.3g}), residual {fit.residual_rms_m * 1e6:.3g} um RMS, "
            f"{t.size / 1e3:.0f} s of trace")
    return [_fig_axis(ident, "x"), _fig_friction(ident, base, "x")], note


def cycle_time() -> tuple[list[str], str]:
    """Planned cycle time over toppra's bound per program of bench/bench_plan.py."""
    import math

    from oga.report.optimize import _GREY, _LIMIT, _OPT, _Panel, _svg

    spec = importlib.util.spec_from_file_location("bench_plan", ROOT / "bench" / "bench_plan.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    limits = bench.MACHINE.planning_limits()
    rows = []
    for name, text in bench.programs(SHARED, None):
        r = bench.measure(name, text, limits, True)
        if r["toppra_s"] > 0:
            rows.append((name, r["plan_s"], r["toppra_s"]))
    top = max(2.0, math.ceil(max(p / b for _, p, b in rows) * 2) / 2)
    h = 24 * len(rows)
    panel = _Panel(230, 28, 820, h, (1.0, top), (0, len(rows)))
    for k, (name, p, b) in enumerate(rows):
        y0, y1 = panel.py(len(rows) - k - 0.2), panel.py(len(rows) - k - 0.8)
        x1 = panel.px(p / b)
        panel.parts.append(f'<rect x="{panel.x0}" y="{y0:.1f}" width="{x1 - panel.x0:.1f}" '
                           f'height="{y1 - y0:.1f}" fill="{_OPT}"/>')
        panel.text(panel.x0 - 8, (y0 + y1) / 2 + 4, name, anchor="end")
        panel.text(x1 + 4, (y0 + y1) / 2 + 4, f"{p / b:.3f} ({p:.1f} s)", _GREY)
    panel.vline(1.0, _LIMIT, dash=None)
    panel.legend([("planned cycle time / toppra's bound (no jerk limit: not reachable)", _OPT)])
    body = panel.render("planned / bound", "").replace('font-size="10" text-anchor="end">',
                                                       'font-size="0" text-anchor="end">')
    note = ", ".join(f"{n} {p / b:.3f}" for n, p, b in rows)
    return [_svg(1100, h + 70, body, "cycle time")], note


FIGURES = {"contour-error": contour_error, "certificate": certificate,
           "identification-fit": identification_fit, "cycle-time": cycle_time}


def rasterise(svgs: list[str], png: Path) -> None:
    """The SVGs (or HTML holding them) stacked top to bottom, as one PNG (headless Chromium)."""
    from playwright.sync_api import sync_playwright

    html = ('<!DOCTYPE html><html><body style="margin:0;background:#fff">'
            '<div id="fig" style="display:inline-block;background:#fff">'
            + "".join(f"<div>{s}</div>" for s in svgs) + "</div></body></html>")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM,
                                     args=["--headless", "--no-sandbox", "--disable-gpu"])
        page = browser.new_page(viewport={"width": 1100, "height": 800})
        page.set_content(html)
        page.locator("#fig").screenshot(path=str(png))
        browser.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", choices=[[], *FIGURES], metavar="NAME",
                    help=f"figures to draw (default all: {', '.join(FIGURES)})")
    ap.add_argument("--shared", type=Path, default=SHARED,
                    help="the shared folder holding toolpaths/external (cycle-time)")
    args = ap.parse_args(argv)
    globals()["SHARED"] = args.shared
    OUT.mkdir(parents=True, exist_ok=True)
    host = f"{platform.node()}, {platform.processor() or platform.machine()}, " \
           f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}"
    for name in args.names or FIGURES:
        c0 = time.process_time()
        svgs, note = FIGURES[name]()
        rasterise(svgs, OUT / f"{name}.png")
        print(f"{name}.png ({datetime.date.today()}, {host}; {time.process_time() - c0:.1f} s "
              f"CPU): {note}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
