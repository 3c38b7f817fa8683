"""The identified machine: the base machine with the fitted cascades and dead times, its
uncertainty section from the confidence intervals and the evidence of model error, and its
TOML text with every interval beside it.
"""

from __future__ import annotations

import math
from collections import Counter

from oga.defaults import (
    IDENT_BOUNDS,
    IDENT_CONFIDENCE,
    IDENT_MODEL_ERROR_MAX_WIDTH,
    IDENT_MODEL_ERROR_WIDTHS,
    IDENT_UNCERTAINTY_FLOOR,
    IDENT_UNCERTAINTY_WIDTHS,
)
from oga.identify.fit import PARAMETERS, AxisFit
from oga.model.machine import FACTOR_FIELDS, Machine, Uncertainty, machine_from_dict

__all__ = ["uncertainty_of", "identified_machine", "machine_toml"]

#: Smallest factor the uncertainty section writes.
_MIN_FACTOR = 0.1


#: Largest factor the uncertainty section writes (beyond it the set is no statement), and
#: the most extra dead time.
_MAX_FACTOR = 10.0
_MAX_EXTRA_DEAD = 3


def _physical_range(name: str, mass: float) -> tuple[float, float]:
    """The physical bounds (:data:`oga.defaults.IDENT_BOUNDS`) of cascade field ``name`` on
    an axis of ``mass`` kg: a factor range never leaves them."""
    b = IDENT_BOUNDS
    per_kg = {"coulomb_n": "coulomb_n_per_kg", "viscous_n_s_m": "viscous_1_s"}
    if name == "kv_n_s_m":
        return tuple(2 * math.pi * mass * f for f in b["velocity_loop_hz"])
    if name == "static_n":
        return (0.0, mass * (b["coulomb_n_per_kg"][1] + b["stribeck_rise_n_per_kg"][1]))
    if name in per_kg:
        return tuple(mass * x for x in b[per_kg[name]])
    if name == "mass_kg":
        return (0.0, math.inf)
    return b[name]


def uncertainty_of(fit: AxisFit, *, widths: float = IDENT_UNCERTAINTY_WIDTHS,
                   floor: float = IDENT_UNCERTAINTY_FLOOR, heldout_ratio: float = 1.0,
                   model_widths: float = IDENT_MODEL_ERROR_WIDTHS) -> Uncertainty:
    """Per-parameter factor ranges around the fitted values, grown with the evidence of
    model error.

    Each range covers ``widths`` confidence half-widths each way (the intervals already
    widened by the residual's correlation time: :class:`~oga.identify.fit.AxisFit`), times
    ``heldout_ratio`` where a held-out check predicted the unseen part worse than the fitted
    one (its RMS ratio, at least 1), and at least the larger of ``floor`` and ``model_widths``
    times the larger of the fit's model-error share (what the model leaves out is in no
    parameter alone: every range grows with it) and the parameter's model-error change (the
    change of that parameter alone that moves the positions by the unexplained residual: a
    parameter the trace hardly sees gets a wide range), that part at most
    ``IDENT_MODEL_ERROR_MAX_WIDTH``; at most x0.1-x10 and inside the physical bounds. The mass moves the loop as Kv does. Every piece grows continuously with
    its evidence. Extra dead time: ``model_widths`` times the dead time's model-error change,
    rounded, and at least 1 when one more sample fits within 1 % of the best residual or the
    fit is not ``ok``."""
    out = {}
    grow = max(1.0, heldout_ratio) if math.isfinite(heldout_ratio) else 1.0
    change = fit.model_error_changes
    mass = fit.values["mass_kg"]
    for name in FACTOR_FIELDS:
        least = max(floor, min(IDENT_MODEL_ERROR_MAX_WIDTH, model_widths * max(
            fit.model_error_share, change.get(name, 0.0))))
        v = fit.values[name]
        if v > 0 and math.isfinite(fit.ci_low[name]) and math.isfinite(fit.ci_high[name]):
            lo_rel = widths * grow * (v - fit.ci_low[name]) / v
            hi_rel = widths * grow * (fit.ci_high[name] - v) / v
        else:
            lo_rel = hi_rel = 0.0
        lo = max(_MIN_FACTOR, 1.0 - max(least, lo_rel))
        hi = min(_MAX_FACTOR, 1.0 + max(least, hi_rel))
        if v > 0:
            p_lo, p_hi = _physical_range(name, mass)
            lo, hi = min(1.0, max(lo, p_lo / v)), max(1.0, min(hi, p_hi / v))
        out[name] = (round(lo, 4), round(hi, 4))
    best = fit.residual_rms_m
    more = [rms for d, lag, rms in fit.candidates
            if d == fit.dead_time_samples + 1 and lag == fit.lag_samples]
    doubt = fit.status != "ok" or bool(more and more[0] <= 1.01 * best)
    extra = min(round(model_widths * change.get("dead_time_samples", 0.0)), _MAX_EXTRA_DEAD)
    out["dead_time_extra_samples"] = (0, max(extra, 1 if doubt else 0))
    return Uncertainty(**out, fit_status=fit.status,
                       model_error_share=round(fit.model_error_share, 4))


def _dead_time(fits: dict[str, AxisFit], base: Machine) -> int:
    """The machine's dead time: the whole one most axes fitted (ties: the larger); the
    base's where none fitted a whole one."""
    counts = Counter(f.dead_time_samples for f in fits.values()
                     if float(f.dead_time_samples).is_integer())
    if not counts:
        return base.timing.dead_time_samples
    return int(max(counts, key=lambda d: (counts[d], d)))


def identified_machine(base: Machine, fits: dict[str, AxisFit], name: str | None = None,
                       holdout: dict | None = None) -> Machine:
    """``base`` with each fitted axis's cascade, uncertainty and dead time.

    The machine's ``timing.dead_time_samples`` is the whole dead time most fitted axes
    share; an axis whose own differs (fitted, or the base's on an axis not fitted) carries
    it as its ``dead_time_samples``. ``holdout`` (per axis, :class:`Identification`'s)
    widens the sets by the held-out check.

    Raises
    ------
    MachineError
        The result does not validate (never expected: the fit keeps every bound).
    """
    data = base.model_dump(mode="json", exclude_none=True)
    holdout = holdout or {}
    for a, fit in fits.items():
        data["axes"][a]["cascade"] = fit.cascade.model_dump(mode="json")
        h = holdout.get(a)
        ratio = h["rms_heldout_m"] / max(h["rms_fit_m"], 1e-15) if h else 1.0
        data["axes"][a]["uncertainty"] = uncertainty_of(fit, heldout_ratio=ratio).model_dump(
            mode="json")
    dead = _dead_time(fits, base)
    data["timing"]["dead_time_samples"] = dead
    for a in data["axes"]:
        own = fits[a].dead_time_samples if a in fits else base.dead_time_samples_of(a)
        if float(own) != dead:
            data["axes"][a]["dead_time_samples"] = float(own)
        else:
            data["axes"][a].pop("dead_time_samples", None)
    data["name"] = name or f"{base.name}-identified"
    data["source"] = (f"identified by oga identify from a trace on {base.name}; axes "
                      f"{', '.join(sorted(fits))} fitted, the rest as {base.name}")
    return machine_from_dict(data, where="identified machine")


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v) if isinstance(v, int) else repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return "[" + ", ".join(_value(x) for x in v) + "]"


def machine_toml(machine: Machine, fits: dict[str, AxisFit]) -> str:
    """The machine as TOML that :func:`oga.model.machine.load_machine` reads, each fitted value
    with its confidence interval and the fit's residual in a comment beside it."""
    data = machine.model_dump(mode="json", exclude_none=True)
    pct = f"{IDENT_CONFIDENCE * 100:g} %"
    lines = [f"# {data['name']}: identified by oga identify.",
             f"# Beside each fitted value: its {pct} confidence interval (from the Jacobian at",
             "# the optimum; it holds for the model, not for what the model leaves out).", ""]
    for key in ("name", "source"):
        lines.append(f"{key} = {_value(data[key])}")
    for table in ("timing", "gains", "planner"):
        lines += ["", f"[{table}]"]
        for k, v in data[table].items():
            note = ""
            if table == "timing" and k == "dead_time_samples" and fits:
                found = ", ".join(f"{a}: {f.dead_time_samples:.4g} (+{f.lag_samples} logging "
                                  "lag)" for a, f in sorted(fits.items()))
                note = f"   # fitted per axis {found}"
            lines.append(f"{k} = {_value(v)}{note}")
    for a, ax in data["axes"].items():
        fit = fits.get(a)
        if "dead_time_samples" in ax:  # the axis's own (the timing's is most axes')
            lines += ["", f"[axes.{a}]", f"dead_time_samples = {_value(ax['dead_time_samples'])}"
                      + ("   # fitted" if fit is not None else "   # the base machine's")]
        lines += ["", f"[axes.{a}.limits]"]
        lines += [f"{k} = {_value(v)}" for k, v in ax["limits"].items()]
        for kind in ("cascade", "arx"):
            if kind not in ax:
                continue
            lines += ["", f"[axes.{a}.{kind}]"]
            if fit is not None:
                lines.append(
                    f"# fitted on {fit.n_samples} samples: position residual RMS "
                    f"{fit.residual_rms_m * 1e6:.4g} um (measurement noise about "
                    f"{fit.noise_rms_m * 1e6:.3g} um), status {fit.status}"
                    + ("" if fit.force_residual_rms_n is None else
                       f", force residual RMS {fit.force_residual_rms_n:.4g} N"))
                lines.append(
                    f"# model error: residual {fit.noise_ratio:.3g} times the noise, correlated "
                    f"over {fit.correlation_samples:.3g} samples (1: white), "
                    f"{fit.model_error_share:.3g} of the velocity loop's imprint unexplained"
                    + (f"; on a physical bound: {', '.join(fit.at_bounds)}" if fit.at_bounds
                       else ""))
            for k, v in ax[kind].items():
                note = ""
                if fit is not None and k in PARAMETERS:
                    if k == "mass_kg" and not fit.mass_identified:
                        note = "   # not identifiable without a force channel: the base's"
                    else:
                        note = f"   # {pct} CI [{fit.ci_low[k]:.6g}, {fit.ci_high[k]:.6g}]"
                lines.append(f"{k} = {_value(v)}{note}")
        if "uncertainty" in ax:
            what = ("factor ranges (low, high) on the values above, from the intervals and the "
                    "evidence of model error" if fit is not None else
                    "the base machine's set (this axis was not identified)")
            lines += ["", f"[axes.{a}.uncertainty]   # {what}"]
            lines += [f"{k} = {_value(v)}" for k, v in ax["uncertainty"].items()]
    return "\n".join(lines) + "\n"

