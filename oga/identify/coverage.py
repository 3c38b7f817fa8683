"""What a machine's model says of itself: which axes' sets were identified, and whether the
model covers the plant (for the summary of a table made with it).

``oga identify`` writes, into each fitted axis's uncertainty section, the fit's status and
its model-error share (:class:`oga.model.machine.Uncertainty`): ``ok``, ``model-error`` (the set
widened by the evidence, :func:`oga.identify.write.uncertainty_of`) or ``poor`` (the model
does not explain the trace: a certificate on its set promises nothing on the machine). An
axis whose section has no status carries an assumed set (a preset's, or a user's); an axis
without a section has none (its nominal model alone).
"""

from __future__ import annotations

from oga.model.machine import Machine

__all__ = ["model_coverage"]


def model_coverage(machine: Machine, axes) -> dict:
    """The model's word on ``axes`` (the program's moving axes), JSON-ready.

    Returns
    -------
    dict
        ``covers`` (False where a fit of a moving axis is ``poor``), ``axes``: per axis
        ``set`` (``"identified"``, ``"assumed"`` or ``"none"``), ``fit_status`` and
        ``model_error_share`` (None unless identified) and ``dead_time_samples``; ``note``:
        one sentence for the user ("" where every moving axis is identified ``ok``).
    """
    per_axis = {}
    for a in axes:
        ax = machine.axes.get(a)
        unc = None if ax is None else ax.uncertainty
        kind = ("none" if unc is None else "assumed" if unc.fit_status is None
                else "identified")
        per_axis[a] = {"set": kind, "fit_status": None if unc is None else unc.fit_status,
                       "model_error_share": None if unc is None else unc.model_error_share,
                       "dead_time_samples": (machine.dead_time_samples_of(a) if ax is not None
                                             else None)}
    poor = [a for a, p in per_axis.items() if p["fit_status"] == "poor"]
    widened = [a for a, p in per_axis.items() if p["fit_status"] == "model-error"]
    assumed = [a for a, p in per_axis.items() if p["set"] == "assumed"]
    notes = []
    if poor:
        notes.append(f"the model does not cover the plant on axis {', '.join(poor)} (its "
                     "identification left the trace unexplained): the certificate holds on "
                     "the set, not on the machine")
    if widened:
        notes.append(f"axis {', '.join(widened)}: identified with model error, the set "
                     "widened by the evidence")
    if assumed and len(assumed) < len(per_axis):
        notes.append(f"axis {', '.join(assumed)}: an assumed set (not identified)")
    return {"covers": not poor, "axes": per_axis, "note": "; ".join(notes)}
