"""The identification program: G-code that makes every cascade parameter visible.

Per axis, from the start point (every axis at 0, programme coordinates), inside
``[0, travel]`` on each axis:

1. constant-speed passes in both directions at speeds inside and well above the
   base machine's Stribeck band (:data:`oga.defaults.EXCITE_STRIBECK_MULTIPLES`) and at
   fractions of the axis speed limit (:data:`oga.defaults.EXCITE_VMAX_FRACTIONS`): the
   friction curve (slow passes are shortened to 3 s, ``pass_s``);
2. velocity steps: three collinear moves at rising, then falling feeds, each way;
3. a swept-frequency section: reversing moves at :data:`oga.defaults.EXCITE_SWEEP_HZ`,
   the amplitude limited so the acceleration stays within half the planning limit
   (loop dynamics, dead time, reversals);

then a circle test in each plane the axes span, at two feeds.
"""

from __future__ import annotations

import math

from feedplan.setpoints import AXES
from oga.defaults import (
    EXCITE_STRIBECK_MULTIPLES,
    EXCITE_SWEEP_HZ,
    EXCITE_TRAVEL_MM,
    EXCITE_VMAX_FRACTIONS,
)
from oga.errors import OptionError
from oga.model.machine import Machine

__all__ = ["excite_program"]

#: Longest constant-speed pass, s.
_PASS_S = 3.0
#: Cycles per frequency of the swept section.
_SWEEP_CYCLES = 4
#: Plane of each axis pair: (G-code, centre-offset letters).
_PLANES = {("x", "y"): ("G17", "I", "J"), ("x", "z"): ("G18", "I", "K"),
           ("y", "z"): ("G19", "J", "K")}


def _feed(v_m_s: float) -> str:
    return f"F{v_m_s * 60e3:.4f}"


def excite_program(machine: Machine, axes: list[str], travel_mm: float = EXCITE_TRAVEL_MM, *,
                   pass_s: float = _PASS_S, sweep_hz=EXCITE_SWEEP_HZ) -> str:
    """The identification program of ``axes`` on ``machine`` (G-code, mm, absolute).

    Parameters
    ----------
    machine : Machine
        The base machine (its limits and Stribeck velocity set the speeds).
    axes : list of str
        Axes to identify (each a cascade axis of the machine).
    travel_mm : float
        Free travel per axis in the positive direction from the start point, mm.
    pass_s : float
        Longest constant-speed pass, s (the slow passes last this long each way).
    sweep_hz : sequence of float
        Frequencies of the swept section, Hz (each runs 4 cycles).

    Returns
    -------
    str
        The program; it starts and ends at the start point.

    Raises
    ------
    OptionError
        Unknown, repeated or non-cascade axis, travel out of (1, 10000] mm, a pass not in
        (0, 60] s or a sweep frequency not in (0, 100] Hz.
    """
    _check(machine, axes, travel_mm, pass_s, sweep_hz)
    lim = machine.planning_limits()
    out = [f"(oga excite: identification program for {machine.name}, axes {','.join(axes)}, "
           f"travel {travel_mm:g} mm)", "G21 G90 G94 G17", "G1 " + " ".join(f"{a.upper()}0" for a in axes)
           + f" {_feed(0.01)}"]
    for a in axes:
        out += _axis_section(machine, lim, a, travel_mm, pass_s, sweep_hz)
    out += _circle_sections(lim, axes, travel_mm)
    out += ["G17", "M2"]
    return "\n".join(out) + "\n"


def _check(machine: Machine, axes, travel_mm, pass_s, sweep_hz) -> None:
    """Refuse the arguments of :func:`excite_program` it names (OptionError)."""
    if not axes or len(set(axes)) != len(axes):
        raise OptionError(f"--axes: give distinct axes, got {','.join(axes)}")
    for a in axes:
        if a not in AXES:
            raise OptionError(f"--axes: unknown axis {a!r}; use x, y, z")
        if machine.axis(a).cascade is None:
            raise OptionError(f"--axes: axis {a} of {machine.name} is not a cascade axis")
    if not (1.0 < travel_mm <= 10000.0):
        raise OptionError(f"--travel-mm must be in (1, 10000], got {travel_mm}")
    if not (0.0 < pass_s <= 60.0):
        raise OptionError(f"pass_s must be in (0, 60] s, got {pass_s}")
    if not sweep_hz or not all(0.0 < f <= 100.0 for f in sweep_hz):
        raise OptionError(f"sweep_hz: give frequencies in (0, 100] Hz, got {list(sweep_hz)}")


def _axis_section(machine: Machine, lim, a: str, travel_mm, pass_s, sweep_hz) -> list[str]:
    """The lines of axis ``a``: constant-speed passes, velocity steps, a swept frequency."""
    out = []
    c = AXES.index(a)
    vmax, amax = float(lim.vmax_m_s[c]), float(lim.amax_m_s2[c])
    vs = machine.axis(a).cascade.stribeck_m_s
    speeds = sorted({m * vs for m in EXCITE_STRIBECK_MULTIPLES}
                    | {f * vmax for f in EXCITE_VMAX_FRACTIONS})
    L = a.upper()
    out.append(f"(axis {a}: constant-speed passes, both directions)")
    for v in speeds:
        length = min(travel_mm, v * 1e3 * pass_s)
        out += [f"G1 {L}{length:.4f} {_feed(v)}", f"G1 {L}0"]
    out.append(f"(axis {a}: velocity steps)")
    steps = [f * vmax for f in EXCITE_VMAX_FRACTIONS[1:]]
    for k, v in enumerate(steps):
        out.append(f"G1 {L}{travel_mm * (k + 1) / len(steps):.4f} {_feed(v)}")
    for k, v in enumerate(steps):
        out.append(f"G1 {L}{travel_mm * (len(steps) - k - 1) / len(steps):.4f} {_feed(v)}")
    out.append(f"(axis {a}: swept frequency)")
    mid = travel_mm / 2
    for f in sweep_hz:
        amp_mm = min(travel_mm / 10, 0.5 * amax / (2 * math.pi * f) ** 2 * 1e3)
        v = min(vmax, 4 * amp_mm * 1e-3 * f)
        out.append(f"G1 {L}{mid:.4f} {_feed(vmax / 4)}")
        for _ in range(_SWEEP_CYCLES):
            out += [f"G1 {L}{mid + amp_mm:.4f} {_feed(v)}", f"G1 {L}{mid - amp_mm:.4f}"]
    out.append(f"G1 {L}0 {_feed(vmax / 4)}")
    return out


def _circle_sections(lim, axes, travel_mm) -> list[str]:
    """A circle test in each plane of two identified axes, at 5 and 20 % of the speed limit."""
    out = []
    for pair, (g, i1, i2) in _PLANES.items():
        if pair[0] in axes and pair[1] in axes:
            r = travel_mm / 4
            out.append(f"(circle test in the {pair[0]}{pair[1]} plane, R {r:g} mm)")
            c1, c2 = (AXES.index(p) for p in pair)
            vmax = min(float(lim.vmax_m_s[c1]), float(lim.vmax_m_s[c2]))
            a1, a2 = pair[0].upper(), pair[1].upper()
            out.append(f"G1 {a1}0 {a2}{r:.4f} {_feed(0.05 * vmax)}")  # the centre at (r, r)
            for v in (0.05 * vmax, 0.2 * vmax):
                out.append(f"{g} G2 {a1}0 {a2}{r:.4f} {i1}{r:.4f} {i2}0 {_feed(v)}")
            out.append(f"G1 {a1}0 {a2}0")
    return out
