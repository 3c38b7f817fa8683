"""``compare``: the controllers of the registry side by side on one toolpath and plant.

Every controller (:mod:`oga.controllers`) is simulated on the same setpoints and
machine; each row's figures are computed here from the run's positions and
velocity commands by the same functions for everybody: the contour error
(:func:`oga.model.contour.contour_error_of`) and its statistics over the feed samples
(:func:`oga.model.metrics.contour_metrics`), and the command ratios of paper eq. 2
(:func:`oga.verify.command_ratios`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from feedplan.setpoints import AXES, Setpoints
from oga.model.contour import contour_error_of
from oga.controllers import CONTROLLERS, load_controller
from oga.errors import OgaError, OptimizeError, OptionError, TuneError
from oga.model.machine import Machine
from oga.model.metrics import contour_metrics
from oga.verify.replay import command_ratios, ferror_ratios

__all__ = ["ComparisonRow", "Comparison", "compare", "parse_controllers"]

_UM = 1e6
#: Slack on the limit check (float64 rounding only), as in oga.verify.replay.
_SLACK = 1e-9


@dataclass(frozen=True, eq=False)
class ComparisonRow:
    """One controller's figures on the toolpath.

    Attributes
    ----------
    name : str
        Controller name.
    status : {"ok", "untuned", "failed"}
        ``"untuned"``: tuning was asked but no setting of the controller's grid meets
        the axis limits (:class:`oga.errors.TuneError`); the figures are those of its
        paper/design parameters, which break the limits (``limits_ok`` False).
        ``"failed"``: the controller raised another :class:`oga.errors.OgaError`
        (the figures are then NaN / empty).
    message : str
        Why a row is untuned or failed, else ``""``.
    needs_firmware : bool or None
        Whether it needs drive-firmware access (None when it could not be loaded).
    mse_ce_um2, rms_ce_um, max_ce_um : float
        MSE, RMS and largest |contour error| over the feed samples, um^2 / um.
    track_max_um : dict of str to float
        Largest |pd - p| per axis (x, y, z), um.
    accel_ratio, jerk_ratio : float
        Worst velocity-command acceleration and jerk over the axes, as a ratio to
        the axis limits (paper eq. 2; <= 1 is within).
    velocity_ratio : float
        Same for the velocity command itself.
    limits_ok : bool
        Every ratio <= 1, and the following error within the machine's limit
        (``ferror_max_m``) where it sets one.
    time_s : float
        Wall time of the controller's run (tuning included), s.
    parameters : dict
        The values the controller used.
    notes : tuple of str
        Its assumptions.
    ce_m : ndarray, shape (N,)
        Contour error per sample, m (empty for a failed row).
    """

    name: str
    status: str
    message: str
    needs_firmware: bool | None
    mse_ce_um2: float
    rms_ce_um: float
    max_ce_um: float
    track_max_um: dict
    accel_ratio: float
    jerk_ratio: float
    velocity_ratio: float
    limits_ok: bool
    time_s: float
    parameters: dict
    notes: tuple[str, ...]
    ce_m: np.ndarray

    def to_dict(self) -> dict:
        """JSON-able figures (no per-sample data); NaN figures become None."""

        def num(x):
            return None if not np.isfinite(x) else float(x)

        return {
            "name": self.name,
            "status": self.status,
            "message": self.message,
            "needs_firmware": self.needs_firmware,
            "mse_ce_um2": num(self.mse_ce_um2),
            "rms_ce_um": num(self.rms_ce_um),
            "max_ce_um": num(self.max_ce_um),
            "track_max_um": {a: num(v) for a, v in self.track_max_um.items()},
            "velocity_ratio": num(self.velocity_ratio),
            "accel_ratio": num(self.accel_ratio),
            "jerk_ratio": num(self.jerk_ratio),
            "limits_ok": self.limits_ok,
            "time_s": self.time_s,
            "parameters": _jsonable(self.parameters),
            "notes": list(self.notes),
        }


@dataclass(frozen=True, eq=False)
class Comparison:
    """Every compared controller on one toolpath.

    Attributes
    ----------
    setpoints : Setpoints
        The toolpath's setpoints (N samples).
    machine : str
        Machine name.
    rows : tuple of ComparisonRow
        One per controller, in the order asked.
    """

    setpoints: Setpoints
    machine: str
    rows: tuple[ComparisonRow, ...]

    def to_dict(self) -> dict:
        """The ``oga compare --json`` document."""
        return {
            "toolpath": self.setpoints.source,
            "machine": self.machine,
            "samples": len(self.setpoints),
            "te_s": self.setpoints.dt,
            "controllers": [r.to_dict() for r in self.rows],
        }


def _jsonable(x):
    """Parameters as JSON values (numpy scalars and arrays to Python)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def parse_controllers(text: str) -> tuple[str, ...]:
    """Controller names from a comma-separated list (OptionError on unknown or repeated names)."""
    names = tuple(s.strip() for s in text.split(",") if s.strip())
    if not names:
        raise OptionError(f"controllers: no name given; known: {', '.join(CONTROLLERS)}")
    unknown = [n for n in names if n not in CONTROLLERS]
    if unknown:
        raise OptionError(f"controllers: unknown {', '.join(repr(n) for n in unknown)}; "
                          f"known: {', '.join(CONTROLLERS)}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise OptionError(f"controllers: {', '.join(twice)} given more than once")
    return names


def _failed(name: str, needs_firmware, message: str, t: float) -> ComparisonRow:
    nan = float("nan")
    return ComparisonRow(
        name=name, status="failed", message=message, needs_firmware=needs_firmware,
        mse_ce_um2=nan, rms_ce_um=nan, max_ce_um=nan, track_max_um={a: nan for a in AXES},
        accel_ratio=nan, jerk_ratio=nan, velocity_ratio=nan, limits_ok=False, time_s=t,
        parameters={}, notes=(), ce_m=np.empty(0),
    )


def _row(setpoints: Setpoints, machine: Machine, name: str, tune: bool,
         parameters: dict) -> ComparisonRow:
    t0 = time.perf_counter()
    needs_firmware = None
    try:
        ctl = load_controller(name)
        needs_firmware = ctl.needs_firmware
        status, message = "ok", ""
        try:
            run = ctl.run(setpoints, machine, tune=tune, **parameters)
        except TuneError as err:
            run = ctl.run(setpoints, machine, tune=False, **parameters)
            status, message = "untuned", f"{err} [the row shows the untuned run]"
        if not (np.all(np.isfinite(run.pos)) and np.all(np.isfinite(run.u))):
            raise OptimizeError(
                f"{name}: the closed loop diverged on this plant (positions not finite)"
                + (f"; {message}" if message else "")
            )
        ce = contour_error_of(setpoints, run.pos)
        m = contour_metrics(ce, setpoints.pos, run.pos, setpoints.counted)
        ratios = command_ratios(run.u, setpoints, machine)
    except OgaError as err:
        return _failed(name, needs_firmware, str(err), time.perf_counter() - t0)
    ce.flags.writeable = False
    return ComparisonRow(
        name=name, status=status, message=message, needs_firmware=needs_firmware,
        mse_ce_um2=m.mse_m2 * _UM**2, rms_ce_um=m.rms_m * _UM, max_ce_um=m.max_abs_m * _UM,
        track_max_um={a: v * _UM for a, v in zip(AXES, m.track_max_m)},
        velocity_ratio=float(ratios[:, 0].max()), accel_ratio=float(ratios[:, 1].max()),
        jerk_ratio=float(ratios[:, 2].max()),
        limits_ok=bool(np.isfinite(m.mse_m2) and np.all(ratios <= 1.0 + _SLACK)
                       and not np.any(ferror_ratios(m.track_max_m, machine) > 1.0 + _SLACK)),
        time_s=time.perf_counter() - t0, parameters=dict(run.parameters), notes=run.notes,
        ce_m=ce,
    )


def compare(
    setpoints: Setpoints,
    machine: Machine,
    controllers=CONTROLLERS,
    *,
    tune: bool = True,
    parameters: dict | None = None,
) -> Comparison:
    """Simulate each controller on ``setpoints`` and ``machine`` and tabulate the figures.

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (its period must be the machine's Te).
    machine : Machine
        The plant.
    controllers : sequence of str or str, optional
        Names from :data:`oga.controllers.CONTROLLERS` (a comma-separated string is
        accepted); default all, in the registry's order.
    tune : bool, optional
        Passed to every controller's ``run`` (tune its gains on this toolpath).
    parameters : dict of str to dict, optional
        Parameters per controller name, passed to its ``run``.

    Returns
    -------
    Comparison
        A controller that raises an :class:`oga.errors.OgaError` (including one not
        available in this installation) gets a ``"failed"`` row with the message.

    Raises
    ------
    OptionError
        Unknown or repeated controller name, or parameters for a controller not compared.
    """
    if not isinstance(controllers, str):
        controllers = ",".join(controllers)
    names = parse_controllers(controllers)
    parameters = dict(parameters or {})
    extra = sorted(set(parameters) - set(names))
    if extra:
        raise OptionError(f"parameters: given for controller(s) not compared: {', '.join(extra)}")
    rows = tuple(_row(setpoints, machine, n, tune, dict(parameters.get(n, {}))) for n in names)
    return Comparison(setpoints=setpoints, machine=machine.name, rows=rows)
