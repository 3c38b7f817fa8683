"""A lincurve law exported as HAL runs in LinuxCNC's own HAL (``halrun``, POSIX non-realtime)
and gives oga's velocity command sample for sample.

The bench: ``streamer`` stands in for motion (per axis: the position command, the setpoint
velocity for ``command-deriv``, the same velocity and the setpoint acceleration for the law's
input pins, and oga's simulated positions as feedback), the exported ``oga_law.hal`` (``abs`` and two ``lincurve`` per axis)
runs after it and before ``pid``, and ``sampler`` records ``pid.N.output``, ``Pgain`` and
``FF1``. Needs ``linuxcnc-uspace`` (``.ci/run`` installs it): without ``halrun`` it fails,
never skips.
"""

from __future__ import annotations

import fcntl
import functools
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

from feedplan.read import load_toolpath
from feedplan.setpoints import AXES
from oga.law.export.linuxcnc import LAW_HAL, law_hal
from oga.law.law import AxisLaw, Law, law_gains, signed_acc
from oga.law.override import plan_override
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine
from oga.model.response import simulate
from test_linuxcnc import _LOCK, _halrun_env, _isolated

DATA = Path(__file__).parent / "data"
#: Outputs sampled times 2**40, gains times 2**30 (exact scalings): halsampler prints 6 decimals.
SCALE_U, SCALE_K = 2.0**40, 2.0**30


@functools.cache
def _case(kind):
    """A program at 120 % feed on ucp710, a law whose Kp and Kf both vary (not searched: any
    law within the ranges is what HAL must reproduce), and oga's replay. ``lincurve``: Kp and
    Kf in ``|v|`` on short_xz; ``lincurve-sa``: Kf in the signed acceleration ``a sign(v)``
    on zigzag_xz (both axes speed up and brake in both directions)."""
    machine = load_machine("ucp710")
    prog = "zigzag_xz" if kind == "lincurve-sa" else "short_xz"
    sp = plan_override(load_toolpath(DATA / f"{prog}.ngc"), machine, 1.2, 2e-5)
    axes = {}
    for a, kp, kf in (("x", [1.2, 2.0, 1.6, 1.9], [0.95, 0.85, 0.9, 0.7]),
                      ("z", [1.9, 1.3, 1.7, 1.5], [0.8, 0.9, 0.75, 0.88])):
        i = AXES.index(a)
        vmax, amax = float(np.abs(sp.vel[:, i]).max()), float(np.abs(sp.acc[:, i]).max())
        acc = np.array([-0.6, -0.1, 0.1, 0.6]) * amax if kind == "lincurve-sa" else np.zeros(1)
        axes[a] = AxisLaw(v_m_s=np.array([0.0, 0.2, 0.55, 0.9]) * vmax, a_m_s2=acc,
                          kp_m_min_per_mm=np.array([kp]), kf=np.array([kf]))
    law = Law(kind=kind, axes=axes, fixed_kp={"y": 1.3}, fixed_kf={"y": 0.9})
    kp, kf = law_gains(law, sp)
    sim = simulate(sp, machine, kp, kf)
    return sp, law, kp, kf, sim


def _run(sp, law, feedback, units="mm"):
    """The exported law in halrun, ``feedback`` (N, 3) the positions fed back (m); returns per
    axis the sampled output (m/s), Pgain and FF1."""
    assert shutil.which("halrun"), "halrun missing: install linuxcnc-uspace (.ci/run does)"
    unit = {"mm": 1e-3, "inch": 0.0254}[units]
    axes = [a for a in AXES if a in law.axes]
    n = len(sp)
    cols = []
    for a in axes:  # cmd, vel, vel and acc (the law's inputs), feedback
        i = AXES.index(a)
        cols += [sp.pos[:, i] / unit, sp.vel[:, i] / unit, sp.vel[:, i] / unit,
                 feedback[:, i] / unit, sp.acc[:, i] / unit]
    hal = law_hal(law, ["a test law"], units=units,
                  velocity_pins={a: f"streamer.0.pin.{5 * k + 2}" for k, a in enumerate(axes)},
                  acceleration_pins={a: f"streamer.0.pin.{5 * k + 4}"
                                     for k, a in enumerate(axes)})
    root = Path(tempfile.mkdtemp(prefix="oga-law-hal-"))
    try:
        root.chmod(0o777)
        (root / LAW_HAL).write_text(hal)
        data = np.column_stack(cols)
        (root / "law.stream").write_text(
            "\n".join(" ".join(repr(float(x)) for x in row) for row in data) + "\n")
        names = []
        lines = ["loadrt threads name1=servo-thread period1=1000000 fp1=1",
                 f"loadrt pid num_chan={len(axes)}",
                 f"loadrt streamer depth={n + 1} cfg={'f' * data.shape[1]}",
                 "addf streamer.0 servo-thread",
                 f"source {LAW_HAL}"]
        for k, a in enumerate(axes):
            lines += [f"addf pid.{k}.do-pid-calcs servo-thread",
                      f"setp pid.{k}.enable 1",
                      f"setp pid.{k}.error-previous-target 0",
                      f"net t-{a}-cmd streamer.0.pin.{5 * k} => pid.{k}.command",
                      f"net t-{a}-vel streamer.0.pin.{5 * k + 1} => pid.{k}.command-deriv",
                      f"net t-{a}-fb streamer.0.pin.{5 * k + 3} => pid.{k}.feedback"]
            for what, src, scale in (("u", f"t-{a}-u-in pid.{k}.output", SCALE_U),
                                     ("kp", f"oga-law-{a}-pgain", SCALE_K),  # the law's nets
                                     ("kf", f"oga-law-{a}-ff1", SCALE_K)):
                s = f"t-{a}-{what}"
                names.append(s)
                lines += [f"net {src} => {s}-s.in", f"setp {s}-s.gain {scale!r}",
                          f"net {s}-out {s}-s.out => sampler.0.pin.{len(names) - 1}"]
        lines = (lines[:5] + [f"loadrt scale names={','.join(s + '-s' for s in names)}",
                              f"loadrt sampler depth={n + 10} cfg={'f' * len(names)}"]
                 + lines[5:]
                 + [f"addf {s}-s servo-thread" for s in names]
                 + ["addf sampler.0 servo-thread",
                    "loadusr -w timeout 60 halstreamer -c 0 law.stream",
                    "start",
                    f"loadusr -w timeout 120 halsampler -c 0 -n {n} out.txt"])
        (root / "test.hal").write_text("\n".join(lines) + "\n")
        with open(_LOCK, "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            proc = subprocess.run([*_isolated(), "halrun", "-f", "test.hal"], cwd=root,
                                  env=_halrun_env(root), capture_output=True, text=True,
                                  timeout=180)
        out = root / "out.txt"
        assert proc.returncode == 0 and out.exists(), proc.stdout + proc.stderr
        rows = np.array([r.split() for r in out.read_text().splitlines()], dtype=np.float64)
        assert rows.shape == (n, len(names))
        res = {}
        for k, a in enumerate(axes):
            res[a] = (rows[:, 3 * k] / SCALE_U * unit, rows[:, 3 * k + 1] / SCALE_K,
                      rows[:, 3 * k + 2] / SCALE_K)
        return res
    finally:
        shutil.rmtree(root, ignore_errors=True)


@pytest.mark.parametrize("kind, units", [("lincurve", "mm"), ("lincurve", "inch"),
                                         ("lincurve-sa", "mm")])
def test_law_in_hal_gives_the_velocity_command(kind, units):
    sp, law, kp, kf, sim = _case(kind)
    axes = [a for a in AXES if a in law.axes]
    got = _run(sp, law, sim.pos, units)
    for a in axes:
        i = AXES.index(a)
        u, pgain, ff1 = got[a]
        # the gains: lincurve's arithmetic is the law's (oga.law.law.interp), on the same
        # input up to the units' scaling (one rounding of |v| / unit)
        kp_si = kp[:, i] * KP_SI_PER_M_MIN_PER_MM
        assert np.ptp(kp_si) > 5.0 and np.ptp(kf[:, i]) > 0.05  # the law adapts
        if kind == "lincurve-sa":  # speeding up and braking both run, in both directions
            s = signed_acc(sp.vel[:, i], sp.acc[:, i])
            for d in (1.0, -1.0):
                moving = sp.vel[:, i] * d > 0
                assert (moving & (s > 0.3 * s.max())).any()
                assert (moving & (s < 0.3 * s.min())).any()
        assert np.allclose(pgain, kp_si, rtol=1e-9, atol=0), np.abs(pgain - kp_si).max()
        assert np.allclose(ff1, kf[:, i], rtol=1e-9, atol=0), np.abs(ff1 - kf[:, i]).max()
        # the command, sample for sample: 1e-9 of the loop's terms plus the rounding of the
        # two positions to machine units
        pd, p = sp.pos[:, i], sim.pos[:, i]
        terms = np.abs(kp_si * (pd - p)) + np.abs(kf[:, i] * sp.vel[:, i])
        floor = kp_si * np.finfo(float).eps * (np.abs(pd) + np.abs(p)) * 4
        err = np.abs(u - sim.u[:, i])
        assert (err <= 1e-9 * terms + floor + 1e-15).all(), (a, float(err.max()))
