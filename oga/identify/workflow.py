"""``oga.identify(...)``: a trace and a base machine in, the identified machine out."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from oga.errors import InputError
from oga.identify.fit import AxisFit, axis_inputs, check_fit_input, fit_axis
from oga.identify.trace import AxisTrace, Trace
from oga.identify.write import identified_machine, machine_toml
from oga.model.machine import Machine

__all__ = ["Identification", "identify", "axes_to_fit", "identification_from_summary"]

#: Fit statuses from best to worst.
_STATUSES = ("ok", "model-error", "poor")


@dataclass(frozen=True, eq=False)
class Identification:
    """The result of :func:`identify`.

    Attributes
    ----------
    status : {"ok", "model-error", "poor"}
        The worst of the axes' fits (:class:`AxisFit`): ``model-error`` where a fit explains
        its trace only in part (its set widened), ``poor`` where the model does not cover
        the plant.
    machine : Machine
        The identified machine (loads like any other once written): its sets grown with the
        evidence of model error, the held-out check's included.
    toml : str
        Its machine file, intervals and residuals beside the values.
    fits : dict[str, AxisFit]
    holdout : dict[str, dict]
        Per axis, where a held-out check ran: ``fraction`` of the trace held out (its
        end), ``rms_fit_m`` on the part fitted, ``rms_heldout_m`` predicted on the rest.
    trace : Trace
    base : Machine
        The base machine the fit started from.
    time_s : float
    """

    status: str
    machine: Machine
    toml: str
    fits: dict
    holdout: dict
    trace: Trace
    base: Machine
    time_s: float

    def summary(self) -> dict:
        """JSON-ready summary: status, dead time, per-axis values, intervals, residuals."""
        return {
            "status": self.status,
            "machine": self.machine.name,
            "dead_time_samples": self.machine.timing.dead_time_samples,
            "dead_time_samples_per_axis": {a: self.machine.dead_time_samples_of(a)
                                           for a in self.machine.axes},
            "time_s": self.time_s,
            "axes": {a: {
                "status": f.status, "dead_time_samples": f.dead_time_samples,
                "lag_samples": f.lag_samples, "mass_identified": f.mass_identified,
                "residual_rms_m": f.residual_rms_m, "noise_rms_m": f.noise_rms_m,
                "force_residual_rms_n": f.force_residual_rms_n,
                "values": f.values, "ci_low": f.ci_low, "ci_high": f.ci_high,
                "candidates": [list(c) for c in f.candidates], "fit_time_s": f.fit_time_s,
                "noise_ratio": f.noise_ratio, "correlation_samples": f.correlation_samples,
                "model_error_share": f.model_error_share, "at_bounds": list(f.at_bounds),
                **({"holdout": self.holdout[a]} if a in self.holdout else {}),
            } for a, f in self.fits.items()},
        }


def identification_from_summary(summary: dict, trace: Trace, base: Machine,
                                toml: str) -> Identification:
    """The :class:`Identification` a stored job stands for, rebuilt from what it stored (no
    fit runs again): its :meth:`~Identification.summary`, its trace, base machine and
    identified machine file (``toml``). For the report of a finished job.

    Raises
    ------
    InputError
        MachineError for a machine file that does not load; a summary without its keys.
    """
    import math
    import tomllib

    from oga.model.machine import machine_from_dict

    def numbers(table: dict) -> dict:  # a stored summary holds None for inf and nan (JSON)
        return {k: math.nan if v is None else float(v) for k, v in table.items()}

    try:
        machine = machine_from_dict(tomllib.loads(toml), where="identified machine")
        fits = {}
        for a, s in summary["axes"].items():
            fits[a] = AxisFit(
                status=s["status"], cascade=machine.axis(a).cascade,
                dead_time_samples=s["dead_time_samples"], lag_samples=int(s["lag_samples"]),
                values=numbers(s["values"]), ci_low=numbers(s["ci_low"]),
                ci_high=numbers(s["ci_high"]),
                mass_identified=bool(s["mass_identified"]), residual_rms_m=s["residual_rms_m"],
                noise_rms_m=s["noise_rms_m"], force_residual_rms_n=s["force_residual_rms_n"],
                candidates=[tuple(c) for c in s["candidates"]], fit_time_s=s["fit_time_s"],
                n_samples=trace.n - int(s["lag_samples"]),
                correlation_samples=float(s.get("correlation_samples", 1.0)),
                model_error_share=float(s.get("model_error_share", 0.0)),
                at_bounds=tuple(s.get("at_bounds", ())))
        holdout = {a: s["holdout"] for a, s in summary["axes"].items() if "holdout" in s}
        return Identification(status=summary["status"], machine=machine, toml=toml, fits=fits,
                              holdout=holdout, trace=trace, base=base, time_s=summary["time_s"])
    except (KeyError, TypeError, ValueError, tomllib.TOMLDecodeError) as err:
        if isinstance(err, InputError):
            raise
        raise InputError(f"the stored identification is incomplete: {err!r}") from None


def _head(tr: AxisTrace, n: int) -> AxisTrace:
    cut = {k: (None if v is None else v[:n]) for k, v in vars(tr).items()}
    return AxisTrace(**cut)


def axes_to_fit(trace: Trace, machine: Machine, axes=None) -> list[str]:
    """The axes :func:`identify` fits: ``axes``, or every axis the trace moves by 10 um or
    more; InputError if one is not in the trace or fails
    :func:`~oga.identify.fit.check_fit_input` (a check before a fit is queued)."""
    names = ([a for a, tr in trace.axes.items() if np.ptp(tr.cmd_m) >= 1e-5] if axes is None
             else list(axes))
    if not names:
        raise InputError("no axis moves in the trace (by 10 um or more)")
    for a in names:
        if a not in trace.axes:
            raise InputError(f"axis {a}: not in the trace (it has {', '.join(trace.axes)})")
        check_fit_input(machine, a, trace.axes[a], trace.dt_s)
    return names


def identify(trace: Trace, machine: Machine, *, axes=None, name: str | None = None,
             holdout_fraction: float = 0.0, progress=None) -> Identification:
    """Fit every cascade parameter of the traced axes of ``machine`` to ``trace``.

    Parameters
    ----------
    trace : Trace
        From :func:`oga.identify.trace.read_trace`; its period must be the machine's Te.
    machine : Machine
        The base machine: limits, gains settings and the starting values.
    axes : iterable of str, optional
        Axes to fit (default every axis the trace moves).
    name : str, optional
        Name of the identified machine (default ``<base>-identified``).
    holdout_fraction : float
        If > 0, a second fit on the trace without its last ``holdout_fraction``, whose
        prediction of the rest is the held-out check (costs a second fit).
    progress : callable, optional
        Called with the fraction done (0..1, never falling) at least every
        ``IDENT_PROGRESS_EVERY_S`` of work, each fit an equal share; 1 at the end. An
        exception it raises ends the identification (a cancelled job).

    Returns
    -------
    Identification

    Raises
    ------
    InputError
        An axis not in the trace or the machine, or not a cascade; a bad trace.
    """
    t0 = time.process_time()
    names = axes_to_fit(trace, machine, axes)
    if not (0.0 <= holdout_fraction < 0.9):
        raise InputError(f"holdout_fraction must be in [0, 0.9), got {holdout_fraction}")
    n_fits = len(names) * (2 if holdout_fraction > 0 else 1)

    def share(k: int):
        """The progress of fit ``k`` of ``n_fits`` as a share of the whole."""
        if progress is None:
            return None
        return lambda f: progress(min((k + f) / n_fits, 1.0))

    fits: dict[str, AxisFit] = {a: fit_axis(machine, a, trace.axes[a], trace.dt_s,
                                            progress=share(k)) for k, a in enumerate(names)}
    holdout = {}
    if holdout_fraction > 0:
        from oga.model.simulate import axis_params, simulate_axis

        n_fit = int(round(trace.n * (1 - holdout_fraction)))
        for k, a in enumerate(names):
            part = fit_axis(machine, a, _head(trace.axes[a], n_fit), trace.dt_s,
                            progress=share(len(names) + k))
            cmd, ff, kp, kf = axis_inputs(trace.axes[a], trace.dt_s)
            meas = trace.axes[a].act_m
            p, _ = simulate_axis(axis_params(identified_machine(machine, {a: part}), a), meas[0],
                                 cmd, ff, kp, kf)
            lag = part.lag_samples
            res = p[: p.size - lag] - meas[lag:]
            cut = n_fit - lag
            holdout[a] = {"fraction": holdout_fraction,
                          "rms_fit_m": float(np.sqrt(np.mean(res[:cut] ** 2))),
                          "rms_heldout_m": float(np.sqrt(np.mean(res[cut:] ** 2)))}
    ident = identified_machine(machine, fits, name, holdout)
    status = max((f.status for f in fits.values()), key=_STATUSES.index)
    return Identification(status=status, machine=ident, toml=machine_toml(ident, fits), fits=fits,
                          holdout=holdout, trace=trace, base=machine, time_s=time.process_time() - t0)
