"""The identified machine: the base machine with the fitted cascades, its uncertainty
section from the confidence intervals, and its TOML text with every interval beside it.
"""

from __future__ import annotations

import math
from collections import Counter

from oga.defaults import IDENT_CONFIDENCE, IDENT_UNCERTAINTY_FLOOR, IDENT_UNCERTAINTY_WIDTHS
from oga.identify.fit import PARAMETERS, AxisFit
from oga.machine import FACTOR_FIELDS, Machine, Uncertainty, machine_from_dict

__all__ = ["uncertainty_of", "identified_machine", "machine_toml"]

#: Smallest factor the uncertainty section writes.
_MIN_FACTOR = 0.1


def uncertainty_of(fit: AxisFit, *, widths: float = IDENT_UNCERTAINTY_WIDTHS,
                   floor: float = IDENT_UNCERTAINTY_FLOOR) -> Uncertainty:
    """Per-parameter factor ranges around the fitted values: ``widths`` confidence
    half-widths each way, at least ``floor`` (relative); the mass when no force was
    recorded gets the floor (positions fix only the ratios to it, which the other
    ranges carry). Extra dead time (0, 1) when one more sample fits within 1 % of the
    best residual, else (0, 0)."""
    out = {}
    for name in FACTOR_FIELDS:
        v = fit.values[name]
        if v > 0 and math.isfinite(fit.ci_low[name]) and math.isfinite(fit.ci_high[name]):
            lo_rel = widths * (v - fit.ci_low[name]) / v
            hi_rel = widths * (fit.ci_high[name] - v) / v
        else:
            lo_rel = hi_rel = 0.0
        lo = max(_MIN_FACTOR, 1.0 - max(floor, lo_rel))
        hi = 1.0 + max(floor, hi_rel)
        out[name] = (round(lo, 4), round(hi, 4))
    best = fit.residual_rms_m
    more = [rms for d, lag, rms in fit.candidates
            if d == fit.dead_time_samples + 1 and lag == fit.lag_samples]
    out["dead_time_extra_samples"] = (0, 1 if more and more[0] <= 1.01 * best else 0)
    return Uncertainty(**out)


def _dead_time(fits: dict[str, AxisFit], base: Machine) -> int:
    """The machine's dead time: the one most axes fitted (ties: the larger)."""
    if not fits:
        return base.timing.dead_time_samples
    counts = Counter(f.dead_time_samples for f in fits.values())
    return max(counts, key=lambda d: (counts[d], d))


def identified_machine(base: Machine, fits: dict[str, AxisFit], name: str | None = None) -> Machine:
    """``base`` with each fitted axis's cascade and uncertainty, and the fitted dead time.

    Raises
    ------
    MachineError
        The result does not validate (never expected: the fit keeps every bound).
    """
    data = base.model_dump(mode="json", exclude_none=True)
    for a, fit in fits.items():
        data["axes"][a]["cascade"] = fit.cascade.model_dump(mode="json")
        data["axes"][a]["uncertainty"] = uncertainty_of(fit).model_dump(mode="json")
    data["timing"]["dead_time_samples"] = _dead_time(fits, base)
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
    """The machine as TOML that :func:`oga.machine.load_machine` reads, each fitted value
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
                found = ", ".join(f"{a}: {f.dead_time_samples} (+{f.lag_samples} logging lag)"
                                  for a, f in sorted(fits.items()))
                note = f"   # fitted per axis {found}"
            lines.append(f"{k} = {_value(v)}{note}")
    for a, ax in data["axes"].items():
        fit = fits.get(a)
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
            for k, v in ax[kind].items():
                note = ""
                if fit is not None and k in PARAMETERS:
                    if k == "mass_kg" and not fit.mass_identified:
                        note = "   # not identifiable without a force channel: the base's"
                    else:
                        note = f"   # {pct} CI [{fit.ci_low[k]:.6g}, {fit.ci_high[k]:.6g}]"
                lines.append(f"{k} = {_value(v)}{note}")
        if "uncertainty" in ax:
            lines += ["", f"[axes.{a}.uncertainty]   # factor ranges (low, high) on the values above"]
            lines += [f"{k} = {_value(v)}" for k, v in ax["uncertainty"].items()]
    return "\n".join(lines) + "\n"

