"""Benchmark of the feed planner: cycle time against toppra and ruckig, planning speed.

Run: ``python bench/bench_plan.py [--only NAME,...] [--no-toppra] [--shared DIR]`` from the
repository root (toppra is a dev dependency: ``pip install -e '.[dev]'``). A benchmark, not a
test: it prints figures and asserts nothing.

Programs: those of tests/data (reference_xz, circle_r50_f3000, helix_r20, freeform_xz,
cncjs_toolpath), the LinuxCNC programs of ``shared/toolpaths/external`` (GPL: read from
``--shared``, default ``../shared`` beside the repository, never copied into it; skipped
when absent), and generated freeform programs of 2k, 20k and 100k G1 micro-segments
(:func:`synthetic_program`). Everything at ucp710's planning limits, as ``oga plan`` plans.

Columns of the first table, per program:

- ``plan_s``: planned cycle time (duration of the setpoints);
- ``toppra_s``: toppra's time-optimal parameterisation along the planner's own geometry
  (the very blocks :func:`feedplan.plan.plan` moved along, as ``blocks_of`` returned them
  to it: programmed lines and arcs, the fitted splines of micro-segment runs and chords,
  the corner blends), at rest where the planner stops (block ends), with the per-axis
  velocity and acceleration limits and the path speed at most the programmed feed (times
  ``1 + SPEED_MARGIN``, what the planner's check allows); no jerk limit, and nothing at
  the joints of pieces inside a block (a kink there is free). The planner moves along
  the same curves (within the tolerance the filter rounds them by), stops at the same
  places and honours the same limits plus the jerk limits, so this is a lower bound of
  its cycle time: their ratio is what the planner loses to jerk and to its own
  construction. Why the fitted geometry and not the programmed polyline: along a
  polyline every vertex is a kink, where a time-optimal parameterisation must stop
  (infinite curvature) or, with nothing at the joints, may pass at any speed; the fitted
  and blended curve is the geometry actually run. A failed toppra solve is reported as
  ``failed`` in the row;
- ``straight``: the planner's blocks that are one line (rapids, lone feed lines: not
  blended with a neighbour; straight runs of micro-segments at one feed), their count, the
  planned time of those blocks (each planned alone, as the planner plans them from rest
  to rest) and ruckig's time-optimal jerk-limited rest-to-rest time for them
  (:func:`rest_to_rest_s`, the axis limits projected on the line, speed at most the feed);
- ``dev_um``: largest distance of a feed sample to the programmed geometry;
  ``v/a/j``: worst finite-difference ratio to the limits over the axes;
- ``wall_s``, ``cpu_s``: wall-clock and process CPU time of parsing plus planning.

With ``--jerk`` (about an hour: IPOPT), the first table also gives the jerk-limited reference of
``bench/bench_jerk_reference.py`` along the same blocks, at the planning limits (``jerk_s``, the
machine's ``[planner]`` shares: ``p/jerk`` is the planner's own loss) and at the full axis limits
(``jfull_s``, ``p/jfull``), and ``reserve`` = ``jerk_s / jfull_s``, what the shares cost; then
the blocks where ``p/jerk`` is largest.

The second table splits the CPU time (one core; numba compiled before timing) into the
stages: ``read`` (G-code to Path), ``fit`` (blocks and micro-segment splines,
``blocks_of``), ``plan`` (speed profiles, filtering, check-and-slow-down rounds), ``setpoints``
(derivatives and the Setpoints object), ``check`` (``check_setpoints``, run after ``plan``).
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
import time
from pathlib import Path as FilePath

import numpy as np
from ruckig import InputParameter, Ruckig, Trajectory

from feedplan.check import SPEED_MARGIN, check_setpoints
from feedplan.gcode import parse_gcode
from feedplan.limits import AxisLimits
from feedplan.path import Line, Path
from feedplan.plan import plan, program_tolerance_m
from oga.defaults import TOL_M
from oga.model.machine import load_machine

ROOT = FilePath(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
MACHINE = load_machine("ucp710")
planner = importlib.import_module("feedplan.plan")  # the module (feedplan.plan is also plan())
#: Programs of tests/data (the shared ones the repository may hold).
DATA_PROGRAMS = ("reference_xz.ngc", "circle_r50_f3000.ngc", "helix_r20.ngc", "freeform_xz.ngc",
                 "cncjs_toolpath.nc")
#: LinuxCNC programs of shared/toolpaths/external (GPL-2.0: read there, never copied here).
EXTERNAL = ("lcnc_arcspiral.ngc", "lcnc_lathe_pawn.ngc", "lcnc_test_12mmflat.ngc",
            "lcnc_short_segments_0.001.ngc", "lcnc_plasmatest.ngc", "lcnc_51MeanderAve.ngc",
            "lcnc_line-contouring-xz.ngc")
#: Generated micro-segment programs, segments.
SYNTHETIC = (2000, 20000, 100000)
#: toppra grid: about this spacing along a block (m), at least/most this many points.
TOPPRA_GRID_M = 0.25e-3
TOPPRA_POINTS = (50, 40000)


def rest_to_rest_s(length_m: float, v: float, a: float, j: float) -> float:
    """Duration of the 1-D time-optimal jerk-limited rest-to-rest move (ruckig)."""
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [length_m]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v], [a], [j]
    traj = Trajectory(1)
    Ruckig(1).calculate(inp, traj)
    return traj.duration


def synthetic_program(n: int = 20000) -> str:
    """An XZ freeform finishing pass of ``n`` G1 segments, 0.05 mm in X, rounded to 1 um."""
    x = np.arange(n + 1) * 0.05
    z = 2.0 * np.sin(2 * np.pi * x / 40.0) + 0.8 * np.sin(2 * np.pi * x / 9.0 + 1.0)
    lines = [f"(synthetic freeform, {n} segments)", "G21 G90 G18 G94", f"G0 X0.000 Z{z[0]:.3f}"]
    lines.append("G1 F3000")
    lines += [f"G1 X{a:.3f} Z{b:.3f}" for a, b in zip(x[1:], z[1:])]
    lines.append("M2")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- references


def _projected(d: np.ndarray, lim: np.ndarray) -> float:
    m = np.abs(d) > 1e-12
    return float(np.min(lim[m] / np.abs(d[m])))


def straight_blocks(path: Path, limits: AxisLimits, blocks, tol_m: float = TOL_M):
    """The ``blocks`` (those ``plan`` moved along) of one line: (count, planned s, ruckig s),
    each planned alone from rest to rest. A straight run of micro-segments at one feed (a
    block whose curve is one line) counts as the line from its start to its end."""
    n, planned, best = 0, 0.0, 0.0
    for blk in blocks:
        first, last = path.segments[blk.segments[0]], path.segments[blk.segments[-1]]
        if not blk.curve.is_line or len({path.segments[i].feed_m_s for i in blk.segments}) > 1:
            continue
        seg = Line(first.start, last.end, first.feed_m_s, rapid=blk.rapid, line=first.line)
        n += 1
        planned += plan(Path(seg.start, (seg,)), limits, tol_m=tol_m).duration
        d = (seg.end - seg.start) / seg.length
        v = _projected(d, limits.vmax_m_s)
        if not seg.rapid:
            v = min(v, seg.feed_m_s)
        best += rest_to_rest_s(seg.length, v, _projected(d, limits.amax_m_s2),
                               _projected(d, limits.jmax_m_s3))
    return n, planned, best


class _BlockPath:
    """A block's curve as a toppra path: x, y, z and the arc length along it (its speed is
    the path speed, held to F). The curve's parameter u is the arc length on lines and
    arcs only (|dr/du| differs from 1 inside a corner blend, by a few per mille on a
    fitted spline): the fourth coordinate's derivatives are |dr/du| and its derivative,
    so that the feed bounds the true path speed (its value, never used by the
    constraints, is u)."""

    def __init__(self, curve) -> None:
        self.curve = curve

    dof = 4

    @property
    def path_interval(self) -> np.ndarray:
        return np.array([0.0, self.curve.length])

    @property
    def waypoints(self):
        return None

    def __call__(self, s, order: int = 0) -> np.ndarray:
        u = np.atleast_1d(np.asarray(s, dtype=float))
        r = self.curve.evaluate(np.clip(u, 0.0, self.curve.length), order=2)
        speed = np.linalg.norm(r[1], axis=1)  # |dr/du|
        col = (u, speed, np.sum(r[1] * r[2], axis=1) / speed)[order]
        out = np.column_stack([r[order], col])
        return out if np.ndim(s) else out[0]

    eval = __call__

    def evald(self, s):
        return self(s, 1)

    def evaldd(self, s):
        return self(s, 2)


def toppra_bound_s(path: Path, limits: AxisLimits, blocks: list) -> tuple[float, str]:
    """toppra's time along the planner's ``blocks`` (those ``plan`` moved along, module
    docstring), s, and "" or why it failed."""
    import toppra
    import toppra.algorithm as algo
    import toppra.constraint as con

    toppra.setup_logging("ERROR")
    total = 0.0
    segs = path.segments
    big = 1e6  # no limit (a rapid's speed, the arc length's acceleration)
    for blk in blocks:
        L = blk.curve.length
        seg_u0, seg_feed = blk.seg_u0, np.array([segs[i].feed_m_s for i in blk.segments])
        # the path speed the planner may reach: the feed and the check's margin over it
        seg_feed = np.where(np.isfinite(seg_feed), seg_feed * (1.0 + SPEED_MARGIN), big)

        def vlim(s, seg_u0=seg_u0, seg_feed=seg_feed):
            k = min(max(int(np.searchsorted(seg_u0, s, side="right")) - 1, 0), len(seg_feed) - 1)
            v = np.append(np.where(limits.present, limits.vmax_m_s, big), seg_feed[k])
            return np.column_stack([-v, v])

        amax = np.append(np.where(limits.present, limits.amax_m_s2, big), big)
        n = int(np.clip(L / TOPPRA_GRID_M, *TOPPRA_POINTS))
        grid = np.unique(np.concatenate([np.linspace(0.0, L, n + 1), blk.curve.u0]))
        inst = algo.TOPPRA([con.JointVelocityConstraintVarying(vlim),
                            con.JointAccelerationConstraint(np.column_stack([-amax, amax]))],
                           _BlockPath(blk.curve), gridpoints=grid, solver_wrapper="seidel")
        _, sd, _ = inst.compute_parameterization(0.0, 0.0)
        if sd is None:
            return math.nan, f"toppra failed on the block at line {segs[blk.segments[0]].line}"
        sd = np.maximum(sd, 0.0)  # path speed du/dt at the grid points
        with np.errstate(divide="ignore"):
            total += float(np.sum(2.0 * np.diff(grid) / (sd[:-1] + sd[1:])))
    return total, ""


# --------------------------------------------------------------------------- timing


class _Stages:
    """CPU time (s) of the planner's stages, by wrapping its module-level steps."""

    def __init__(self) -> None:
        self.fit = self.setpoints = 0.0
        self._mark = None
        self.blocks: list = []  # the blocks plan() moved along

    def __enter__(self):
        self._blocks, self._deriv = planner.blocks_of, planner.derivatives

        def blocks(*a, **k):
            t = time.process_time()
            out = self._blocks(*a, **k)
            self.fit += time.process_time() - t
            self.blocks = out
            return out

        def deriv(*a, **k):
            self._mark = time.process_time()  # from here to plan()'s return: setpoints
            return self._deriv(*a, **k)

        planner.blocks_of, planner.derivatives = blocks, deriv
        return self

    def __exit__(self, *exc):
        planner.blocks_of, planner.derivatives = self._blocks, self._deriv


class _PerBlock:
    """Planned time (s) of each block: wraps the planner's two block planners."""

    def __init__(self) -> None:
        self.times: list[float] = []

    def __enter__(self):
        self._straight, self._feed = planner._straight, planner._plan_feed

        def wrap(fn, dt_arg):
            def inner(*a, **k):
                p, ln = fn(*a, **k)
                self.times.append((len(p) - 1) * a[dt_arg])
                return p, ln
            return inner

        planner._straight = wrap(self._straight, 2)  # (seg, limits, dt, ...)
        planner._plan_feed = wrap(self._feed, 5)  # (block, path, limits, seg_feed, tol, dt, ...)
        return self

    def __exit__(self, *exc):
        planner._straight, planner._plan_feed = self._straight, self._feed


def measure(name: str, text: str, limits: AxisLimits, toppra: bool, jerk=None) -> dict:
    """Plan one program, check it, time it, compare it with toppra and ruckig; with ``jerk``
    (the reference options of :func:`bench_jerk_reference.add_reference_args`), with the
    jerk-limited reference at ``limits`` (the planner's shares) and at the machine's full axis
    limits too."""
    c0, w0 = time.process_time(), time.perf_counter()
    path = parse_gcode(text, source=name)
    c1 = time.process_time()
    with _Stages() as st, _PerBlock() as pb:
        sp = plan(path, limits)
        c2, w2 = time.process_time(), time.perf_counter()
    c_check = time.process_time()
    chk = check_setpoints(sp, path, limits, tol_m=program_tolerance_m(path, TOL_M))  # G64 P
    c3 = time.process_time()
    row = dict(name=name, samples=len(sp), plan_s=sp.duration, ok=chk.ok, dev_um=chk.max_deviation_m * 1e6,
               vaj=(chk.vel_ratio.max(), chk.acc_ratio.max(), chk.jerk_ratio.max()),
               wall=w2 - w0, cpu=c2 - c0, read=c1 - c0, fit=st.fit,
               setpoints=c2 - st._mark, check=c3 - c_check, violations=chk.violations)
    row["stage_plan"] = row["cpu"] - row["read"] - row["fit"] - row["setpoints"]
    row["straight"] = straight_blocks(path, limits, st.blocks)
    row["toppra_s"], row["toppra_note"] = (math.nan, "not run")
    row["jerk"] = None
    if toppra or jerk is not None:
        try:
            per_block = [toppra_bound_s(path, limits, [blk]) for blk in st.blocks]
            failed = [note for _, note in per_block if note]
            row["toppra_s"] = sum(t for t, _ in per_block)
            row["toppra_note"] = failed[0] if failed else ""
        except Exception as err:  # a failed solve is a row's remark, not a crash
            row["toppra_s"], row["toppra_note"] = math.nan, f"toppra failed: {err}"
    if jerk is not None and math.isfinite(row["toppra_s"]):
        import bench_jerk_reference as jr

        chosen = jr.chosen_blocks(st.blocks, path.segments, pb.times,
                                  [t for t, _ in per_block], jerk.threshold, jerk.top)
        row["jerk"] = {
            "shares": jr.block_references(path, st.blocks, pb.times, limits, chosen, jerk,
                                          toppra=[t for t, _ in per_block]),
            "full": jr.block_references(path, st.blocks, pb.times, MACHINE.axis_limits(), chosen,
                                        jerk)}
    return row


def programs(shared: FilePath, only: set[str] | None) -> list[tuple[str, str]]:
    """(name, G-code) of every benchmarked program that is present."""
    out = [(FilePath(f).stem, (DATA / f).read_text()) for f in DATA_PROGRAMS]
    ext = shared / "toolpaths" / "external"
    out += [(FilePath(f).stem.removeprefix("lcnc_"), (ext / f).read_text())
            for f in EXTERNAL if (ext / f).is_file()]
    out += [(f"micro_{n // 1000}k", synthetic_program(n)) for n in SYNTHETIC]
    return [p for p in out if only is None or p[0] in only]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="comma-separated program names")
    ap.add_argument("--no-toppra", action="store_true", help="skip the toppra bound")
    ap.add_argument("--jerk", action="store_true",
                    help="the jerk-limited reference (IPOPT) at the shares and at the full "
                         "limits (minutes per program)")
    ap.add_argument("--shared", type=FilePath, default=ROOT.parent / "shared",
                    help="the shared folder holding toolpaths/external (default ../shared)")
    import bench_jerk_reference as jr  # here: it imports this module

    jr.add_reference_args(ap)
    args = ap.parse_args(argv)
    only = set(args.only.split(",")) if args.only else None
    limits = MACHINE.planning_limits()
    plan(parse_gcode(synthetic_program(200)), limits)  # compile numba kernels before timing
    check_setpoints(plan(parse_gcode((DATA / DATA_PROGRAMS[0]).read_text()), limits),
                    parse_gcode((DATA / DATA_PROGRAMS[0]).read_text()), limits)
    rows = []
    head = (f"{'program':22s} {'samples':>7s} {'plan_s':>8s} {'toppra_s':>8s} {'ratio':>6s} "
            f"{'jerk_s':>9s} {'p/jerk':>6s} {'jfull_s':>9s} {'p/jfull':>7s} {'reserve':>7s}  "
            f"{'straight n: plan_s / ruckig_s':>31s} {'dev_um':>6s} {'v/a/j ratio':>17s} "
            f"{'wall_s':>7s} {'cpu_s':>7s} ok")
    print(f"{MACHINE.name} planning limits (as `oga plan`: [planner] acceleration "
          f"{MACHINE.planner.accel_fraction:g}, jerk {MACHINE.planner.jerk_fraction:g} of the "
          f"axis limits), tolerance {TOL_M * 1e3:g} mm; load average "
          f"{' '.join(f'{x:.1f}' for x in _load())}")
    print(head)
    print("-" * len(head))
    for name, text in programs(args.shared, only):
        r = measure(name, text, limits, not args.no_toppra, args if args.jerk else None)
        rows.append(r)
        n, sp_s, rk_s = r["straight"]
        straight = f"{n:4d}: {sp_s:9.3f} / {rk_s:9.3f}" if n else "-"
        ratio = r["plan_s"] / r["toppra_s"] if r["toppra_s"] > 0 else math.nan
        ref = "-"
        if r["jerk"] is not None:
            sh, fu = jr.totals(r["jerk"]["shares"]), jr.totals(r["jerk"]["full"])
            ref = (f"{sh['jerk']:8.3f}{'*' if sh['mixed'] else ' '} {r['plan_s'] / sh['jerk']:6.3f} "
                   f"{fu['jerk']:8.3f}{'*' if fu['mixed'] else ' '} "
                   f"{r['plan_s'] / fu['jerk']:7.3f} {sh['jerk'] / fu['jerk']:7.3f}")
        print(f"{name:22s} {r['samples']:7d} {r['plan_s']:8.3f} {r['toppra_s']:8.3f} {ratio:6.3f} "
              f"{ref:>42s}  {straight:>31s} {r['dev_um']:6.2f} "
              f"{'/'.join(f'{x:.3f}' for x in r['vaj']):>17s} "
              f"{r['wall']:7.2f} {r['cpu']:7.2f} {r['ok']}", flush=True)
        for msg in r["violations"]:
            print("    violation:", msg)
        if r["toppra_note"] and not args.no_toppra:
            print("    toppra:", r["toppra_note"])
    if args.jerk:
        print("(jerk_s, jfull_s: the jerk-limited reference at the shares and at the full axis "
              "limits; * toppra's time stands in for the curved blocks planned within "
              f"{1 + args.threshold:g} of it: the ratio is then an upper bound; a block of more "
              f"than --max-nodes {args.max_nodes} nodes is solved in windows with free speed and "
              "acceleration between them (a relaxation: the ratio leans conservative); reserve = "
              "jerk_s / jfull_s, what the shares cost)")
        print()
        print("blocks where planned / jerk at the shares is largest:")
        for r in rows:
            if r["jerk"] is None:
                continue
            worst = sorted(r["jerk"]["shares"], key=lambda b: -b["planned"] / b["jerk"].time_s)
            for b in worst[:3]:
                kind = "line" if b["straight"] else f"{b['pieces']} pieces"
                print(f"  {r['name']:22s} block {b['i']:3d} line {b['line']:5d} ({kind}, "
                      f"{b['length'] * 1e3:7.2f} mm): planned {b['planned']:7.3f} toppra "
                      f"{b['toppra']:7.3f} jerk {b['jerk'].time_s:7.3f} ({b['jerk'].status}) "
                      f"planned/jerk {b['planned'] / b['jerk'].time_s:5.2f}")
    print()
    print("CPU seconds per stage (one core):")
    head = (f"{'program':22s} {'read':>7s} {'fit':>7s} {'plan':>7s} {'setpoints':>9s} "
            f"{'check':>7s} {'total':>7s}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['name']:22s} {r['read']:7.3f} {r['fit']:7.3f} {r['stage_plan']:7.3f} "
              f"{r['setpoints']:9.3f} {r['check']:7.3f} {r['cpu'] + r['check']:7.3f}")
    print()
    lone_lines(limits)
    return 0


def _load() -> tuple[float, ...]:
    try:
        import os

        return os.getloadavg()
    except OSError:  # pragma: no cover
        return (math.nan,) * 3


def lone_lines(limits: AxisLimits) -> None:
    """Lone feed lines (planned by ruckig) against ruckig's rest-to-rest time, one row each."""
    print("lone feed lines at the planning limits: planned vs ruckig (ratio; +3 samples of the "
          "sample grid and the 1e-3 margin)")
    for axis, length_mm, feed in ((0, 0.04, 3000), (0, 1, 10), (0, 1, 1000), (0, 11, 30000),
                                  (0, 11, 1e8), (2, 200, 30000)):
        end = np.zeros(3)
        end[axis] = length_mm * 1e-3
        path = Path(np.zeros(3), (Line(np.zeros(3), end, feed / 60e3, line=1),))
        sp = plan(path, limits)
        v = min(feed / 60e3, float(limits.vmax_m_s[axis]))
        best = rest_to_rest_s(length_mm * 1e-3, v, float(limits.amax_m_s2[axis]),
                              float(limits.jmax_m_s3[axis]))
        print(f"  {'xyz'[axis]} {length_mm:7.2f} mm at F{feed:<10.6g} {sp.duration:8.3f} s "
              f"{best:8.3f} s  {sp.duration / best:6.3f}")


if __name__ == "__main__":
    sys.exit(main())
