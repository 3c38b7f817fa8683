"""A gain law as a LinuxCNC HAL file: ``abs`` and ``lincurve`` components on the commanded
velocity, driving ``pid``'s ``Pgain`` and ``FF1``.

LinuxCNC's ``lincurve`` (``src/hal/components/lincurve.comp``, up to 16 ``x-val-NN`` /
``y-val-NN`` parameters) maps its input to its output piecewise-linearly: below ``x-val-00``
it gives ``y-val-00``, above the last ``x-val`` the last ``y-val``, no extrapolation. Per
axis the file loads one ``abs`` (``|v|``) and one ``lincurve`` for ``Pgain`` (Kp in 1/s:
(m/min)/mm times 1000/60, the same number in mm and inch machines) and one for ``FF1``
(Kf; a ``pl`` law's constant Kf is a ``setp``). The input is the axis's commanded velocity
(default ``joint.N.vel-cmd``, machine units per second, what motion computes this period),
as oga's model evaluates the law on the setpoint velocity ``vd_k`` of the period whose
command ``u_k = Kp_k (pd_k - p_k) + Kf_k vd_k`` it forms: the file's functions must run after
``motion-controller`` and before ``pid.N.do-pid-calcs`` in the servo thread (source it
between those ``addf`` lines). ``tests/test_law_linuxcnc.py`` runs it in ``halrun``.

A ``lincurve-sa`` law's Kf is a function of the signed acceleration ``s = a sign(v)``: two
``lincurve`` of the commanded acceleration ``a`` (default ``joint.N.joint-acc-cmd``,
units/s^2), ``-kf`` for ``v >= 0`` (``Kf(a)``) and ``-kfneg`` mirrored (``Kf(-a)``, its
x-vals negated and reversed), and a ``mux2`` that takes the second where ``abs``'s
``is-negative`` of the velocity is set (``sign(0) = +1`` as :func:`oga.law.law.signed_acc`).
A HAL component loads once: if the configuration already loads ``abs``, ``lincurve`` or
``mux2``, join these ``names=`` (and ``lincurve``'s ``personality=``) to its own line.
"""

from __future__ import annotations

from feedplan.setpoints import AXES
from oga.errors import OptionError
from oga.law.law import Law
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM

__all__ = ["LAW_HAL", "law_hal"]

#: File name of the export.
LAW_HAL = "oga_law.hal"
_UNIT_M = {"mm": 1e-3, "inch": 0.0254}


def law_hal(law: Law, comment: list[str], *, units: str = "mm",
            joints: dict[str, int] | None = None, velocity_pins: dict[str, str] | None = None,
            acceleration_pins: dict[str, str] | None = None,
            thread: str = "servo-thread") -> str:
    """The HAL file of ``law`` (module doc), opening with the ``comment`` lines.

    Parameters
    ----------
    units : {"mm", "inch"}
        The machine's units (the ``x-val`` velocities are in units/s).
    joints : dict of str to int, optional
        pid loop per axis (default 0, 1, ... in x, y, z order of the law's axes).
    velocity_pins : dict of str to str, optional
        The commanded-velocity pin per axis (default ``joint.N.vel-cmd``).
    acceleration_pins : dict of str to str, optional
        The commanded-acceleration pin per axis of a ``lincurve-sa`` law (default
        ``joint.N.joint-acc-cmd``).
    thread : str

    Raises
    ------
    OptionError
        A law of Kp over acceleration (``mac``: no ``lincurve`` of two inputs), or bad units.
    """
    if law.kind == "mac":
        raise OptionError("--kind: a mac law reads |a| too; LinuxCNC's lincurve takes one "
                          "input (export it for Heidenhain, or search a lincurve law)")
    if units not in _UNIT_M:
        raise OptionError(f"--units: mm or inch, got {units!r}")
    axes = [a for a in AXES if a in law.axes]
    joints = joints or {a: j for j, a in enumerate(axes)}
    missing = [a for a in axes if a not in joints]
    if missing:
        raise OptionError(f"--joints: no pid loop given for axis {', '.join(missing)}")
    pins = {a: (velocity_pins or {}).get(a, f"joint.{joints[a]}.vel-cmd") for a in axes}
    signed = law.kind == "lincurve-sa"
    acc_pins = {a: (acceleration_pins or {}).get(a, f"joint.{joints[a]}.joint-acc-cmd")
                for a in axes}
    scale = 1.0 / _UNIT_M[units]
    lines = _header(comment, units, thread, signed)
    curves, personality = [], []
    for a in axes:
        ax = law.axes[a]
        curves.append(f"oga-law-{a}-kp")
        personality.append(len(ax.v_m_s))
        for c in (("kf", "kfneg") if signed else ("kf",)) if ax.kf.size > 1 else ():
            curves.append(f"oga-law-{a}-{c}")
            personality.append(ax.kf.size)
    lines += [f"loadrt abs names={','.join(f'oga-law-{a}-speed' for a in axes)}",
              f"loadrt lincurve names={','.join(curves)} "
              f"personality={','.join(str(p) for p in personality)}"]
    if signed:
        lines.append(f"loadrt mux2 names={','.join(f'oga-law-{a}-ff' for a in axes)}")
    for a in axes:
        lines.append(f"addf oga-law-{a}-speed {thread}")
        lines += [f"addf {c} {thread}" for c in curves if c.startswith(f"oga-law-{a}-")]
        if signed:
            lines.append(f"addf oga-law-{a}-ff {thread}")
    for a in axes:
        ax, j = law.axes[a], joints[a]
        lines += [f"net oga-law-{a}-vel {pins[a]} => oga-law-{a}-speed.in",
                  f"net oga-law-{a}-speed oga-law-{a}-speed.out => oga-law-{a}-kp.in"
                  + (f" oga-law-{a}-kf.in" if ax.kf.size > 1 and not signed else "")]
        lines += _curve_lines(f"oga-law-{a}-kp", ax.v_m_s * scale,
                              ax.kp_m_min_per_mm[0] * KP_SI_PER_M_MIN_PER_MM)
        lines.append(f"net oga-law-{a}-pgain oga-law-{a}-kp.out => pid.{j}.Pgain")
        if signed:
            lines += _signed_kf_lines(a, j, acc_pins[a], ax.a_m_s2 * scale, ax.kf[0])
        elif ax.kf.size > 1:
            lines += _curve_lines(f"oga-law-{a}-kf", ax.v_m_s * scale, ax.kf[0])
            lines.append(f"net oga-law-{a}-ff1 oga-law-{a}-kf.out => pid.{j}.FF1")
        else:
            lines.append(f"setp pid.{j}.FF1 {float(ax.kf[0, 0])!r}")
    return "\n".join(lines) + "\n"



def _curve_lines(name: str, xs, ys) -> list[str]:
    """``setp`` lines of lincurve ``name``'s support points."""
    out = []
    for k, (x, y) in enumerate(zip(xs, ys)):
        out += [f"setp {name}.x-val-{k:02d} {float(x)!r}", f"setp {name}.y-val-{k:02d} {float(y)!r}"]
    return out


def _signed_kf_lines(a: str, j: int, acc_pin: str, xs, ys) -> list[str]:
    """Axis ``a``'s Kf of ``a sign(v)`` (module doc) on ``pid.j.FF1``: ``xs`` the support
    points in machine units/s^2."""
    return (_curve_lines(f"oga-law-{a}-kf", xs, ys)
            + _curve_lines(f"oga-law-{a}-kfneg", -xs[::-1], ys[::-1])
            + [f"net oga-law-{a}-acc {acc_pin} => oga-law-{a}-kf.in oga-law-{a}-kfneg.in",
               f"net oga-law-{a}-kfpos oga-law-{a}-kf.out => oga-law-{a}-ff.in0",
               f"net oga-law-{a}-kfneg oga-law-{a}-kfneg.out => oga-law-{a}-ff.in1",
               f"net oga-law-{a}-braking oga-law-{a}-speed.is-negative => oga-law-{a}-ff.sel",
               f"net oga-law-{a}-ff1 oga-law-{a}-ff.out => pid.{j}.FF1"])


def _header(comment: list[str], units: str, thread: str, signed: bool) -> list[str]:
    """The file's comment block: ``comment``, then units and where to source it."""
    return [f"# {x}" for x in comment] + [
        f"# Units: {units}; x-val in {units}/s of |commanded velocity|, Pgain y-val in 1/s, "
        "FF1 y-val unitless" + (f"; FF1's x-val in {units}/s^2 of the commanded acceleration "
                                "times the sign of the velocity." if signed else "."),
        "# Source this file after 'addf motion-controller " + thread + "' and before the "
        "pid functions are added:",
        "# the law must see this period's commanded velocity, and pid must see this "
        "period's gains.",
        "# Remove your own settings of pid.N.Pgain and pid.N.FF1 (HAL connects a pin once).",
    ]
