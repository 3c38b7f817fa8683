"""A law as Heidenhain support points: the MAC (Motion Adaptive Control) entries of TNCopt.

Heidenhain's iTNC 530 / TNC 640 adapt controller parameters to input quantities of an
axis at support points (PAC over position; MAC "depending on other input quantities such
as velocity or acceleration", up to five controller parameters; entered in TNCopt's input
forms from version 6.0; iTNC 530 HSCI technical manual, software option 142 and the MAC
option). oga's law adapts two parameters: the kv factor of the position loop in
(m/min)/mm (MP1510.x with velocity feedforward; MP1516.x is the kv factor under
velocity semi-feedforward) and the velocity feedforward factor MP1396.x (0.001-0.999,
1 = full feedforward): ``u = kv * following error + factor * v_nominal`` is oga's
``u = Kp e + Kf vd``. Support points: commanded axis velocity in mm/min and acceleration
in m/s^2, bilinear between them, held beyond the outer ones; every value has three
decimals, as rounded before the law was certified (:func:`oga.law.law.quantized`).
The MAC support-point parameter names themselves are not in Heidenhain's public
documentation: the file is a table to type into TNCopt's MAC form, one per axis.
Heidenhain also asks for equal kv factors on interpolating axes with fixed gains; a law
adapts each axis to its own motion, which the certificate covers.
"""

from __future__ import annotations

from feedplan.setpoints import AXES
from oga.errors import OptionError
from oga.law.law import Law

__all__ = ["HEIDENHAIN", "heidenhain_text"]

#: File name of the export.
HEIDENHAIN = "oga_law_heidenhain.txt"


def heidenhain_text(law: Law, comment: list[str]) -> str:
    """The MAC support points of every law axis, one table per axis (module doc).

    Raises
    ------
    OptionError
        A law of another kind (MAC reads ``|v|`` and ``|a|``: not the signed acceleration of
        ``lincurve-sa``).
    """
    if law.kind not in ("mac", "lincurve", "pl"):
        raise OptionError(f"--kind: Heidenhain MAC cannot express a {law.kind} law (it reads "
                          "|v| and |a|; search --kind mac)")
    lines = [f"; {x}" for x in comment]
    for n, a in enumerate(AXES):
        if a not in law.axes:
            continue
        ax = law.axes[a]
        lines += ["", f"[axis {a.upper()}]  MAC: kv factor (MP1516.{n}), feedforward factor "
                  f"(MP1396.{n})",
                  "point  velocity_mm_min  acceleration_m_s2  kv_m_min_per_mm  ff_factor"]
        k = 0
        for j, acc in enumerate(ax.a_m_s2):
            for i, v in enumerate(ax.v_m_s):
                kf = ax.kf[0, 0] if ax.kf.size == 1 else (ax.kf[j, i] if ax.kf.shape[0] > 1
                                                          else ax.kf[0, i])
                lines.append(f"{k:5d}  {v * 60e3:15.3f}  {acc:17.3f}  "
                             f"{ax.kp_m_min_per_mm[j if ax.kp_m_min_per_mm.shape[0] > 1 else 0, i]:15.3f}"
                             f"  {kf:9.3f}")
                k += 1
    return "\n".join(lines) + "\n"
