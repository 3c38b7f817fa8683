"""A ``pl`` law as Beckhoff TwinCAT CNC axis parameters: the dynamic Kv adjustment.

TwinCAT CNC (ISG kernel) interpolates the position controller gain linearly in the axis
velocity between ``(v1, kv1)`` and ``(v2, kv2)`` and holds it beyond them (axis parameters
P-AXIS-00244 ``getriebe[i].dyn_kv.dyn_kv_active``, P-AXIS-00245 ``kv1`` and P-AXIS-00247
``kv2`` in 0.01/s, P-AXIS-00246 ``v1`` and P-AXIS-00248 ``v2`` in um/s for translatory axes,
``v2 > v1 > 0``; Beckhoff Information System, TF5200 axis parameters, "Settings for dynamic
kv adjustment"). The velocity feedforward weighting is ``vorsteuer.vs_v_faktor /
vorsteuer.vs_v_nenner`` (P-AXIS-00228/00229): oga's Kf. A ``pl`` law of two points is exactly
this; its values were rounded to these units before it was certified
(:func:`oga.law.law.quantized`). The static ``getriebe[i].kv`` (P-AXIS-00099) is set to the
law's kv1, what the axis runs if the adjustment is switched off.
"""

from __future__ import annotations

from feedplan.setpoints import AXES
from oga.errors import OptionError
from oga.law.law import Law
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM

__all__ = ["twincat_files"]


def twincat_files(law: Law, comment: list[str], gear: int = 0) -> dict[str, str]:
    """One axis-parameter-list fragment per law axis, ``oga_law_twincat_<axis>.txt``.

    Raises
    ------
    OptionError
        Not a two-point ``pl`` law (TwinCAT's dynamic Kv has exactly two support points).
    """
    if law.kind != "pl" or any(len(ax.v_m_s) != 2 for ax in law.axes.values()):
        raise OptionError("--kind: TwinCAT CNC's dynamic Kv is a pl law of 2 points "
                          "(--kind pl --points 2)")
    head = [f"# {x}" for x in comment]
    out = {}
    for a in AXES:
        if a not in law.axes:
            continue
        ax = law.axes[a]
        kv = [round(float(k) * KP_SI_PER_M_MIN_PER_MM * 100) for k in ax.kp_m_min_per_mm[0]]
        v = [round(float(x) * 1e6) for x in ax.v_m_s]
        g = f"getriebe[{gear}]"
        out[f"oga_law_twincat_{a}.txt"] = "\n".join(head + [
            f"# axis {a}: merge into its axis parameter list (translatory axis: kv in 0.01/s, "
            "v in um/s)",
            f"{g}.kv                      {kv[0]}",
            f"{g}.dyn_kv.dyn_kv_active    1",
            f"{g}.dyn_kv.kv1              {kv[0]}",
            f"{g}.dyn_kv.v1               {v[0]}",
            f"{g}.dyn_kv.kv2              {kv[1]}",
            f"{g}.dyn_kv.v2               {v[1]}",
            f"vorsteuer.vs_v_faktor       {round(float(ax.kf[0, 0]) * 1000)}",
            "vorsteuer.vs_v_nenner       1000",
        ]) + "\n"
    return out
