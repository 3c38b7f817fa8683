"""The machine description: one frozen pydantic model for library, CLI and API.

A machine is a set of linear axes (x, y, z), each with its kinematic limits and
exactly one model of what lies under the position loop: a ``cascade`` (velocity PI,
force-loop lag, mass, friction) or an ``arx`` (an identified discrete velocity-loop
model with an input-equivalent friction and load), the loop timing, and the
settings of the gain ranges. Everything is SI; gains are spoken in the users' unit
(m/min)/mm and named so.

Presets live as TOML files in ``oga/presets/`` (each states the source of its
numbers); users bring their own file with the same fields (TOML or JSON).
"""

from __future__ import annotations

import hashlib
import json
import tomllib
import weakref
from pathlib import Path as FilePath
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

if TYPE_CHECKING:
    from feedplan.limits import AxisLimits

from oga.defaults import (DT_RANGE_S, FRICTION_LINEAR_MAX_SHARE, MACHINE_FIELD_RANGES,
                          MACHINE_MAX_BYTES)
from oga.errors import MachineError
from oga.files import read_limited

__all__ = [
    "KP_SI_PER_M_MIN_PER_MM",
    "Limits",
    "Cascade",
    "Arx",
    "Axis",
    "Uncertainty",
    "Timing",
    "GainSettings",
    "PlannerSettings",
    "Home",
    "Machine",
    "PRESETS",
    "load_machine",
    "machine_from_dict",
    "json_digest",
    "machine_memo",
]

#: 1 (m/min)/mm expressed in 1/s.
KP_SI_PER_M_MIN_PER_MM = 1000.0 / 60.0

_PRESET_DIR = FilePath(__file__).parents[1] / "presets"  # oga/presets
#: Names of the shipped presets.
PRESETS: tuple[str, ...] = tuple(sorted(p.stem for p in _PRESET_DIR.glob("*.toml")))



def _in(name: str):
    """A float within ``MACHINE_FIELD_RANGES[name]`` (the plausible range, inclusive)."""
    lo, hi = MACHINE_FIELD_RANGES[name]
    return Annotated[float, Field(ge=lo, le=hi, allow_inf_nan=False)]


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Limits(_Frozen):
    """Limits of one axis (SI).

    ``vmax_m_s``, ``amax_m_s2``, ``jmax_m_s3`` bound the velocity command (paper eq. 2).
    ``ferror_max_m``, optional, is the largest following error ``|pd - p|`` the
    controller's following-error monitor tolerates on the axis (LinuxCNC's ``FERROR``,
    which grows with speed from ``MIN_FERROR``: give the least of them). When it is
    set, the best fixed gains, the search and the verification keep every sample (rapids
    included) within it; when unset, nothing bounds the following error (it is reported).
    """

    vmax_m_s: _in("vmax_m_s")
    amax_m_s2: _in("amax_m_s2")
    jmax_m_s3: _in("jmax_m_s3")
    ferror_max_m: _in("ferror_max_m") | None = None


class Cascade(_Frozen):
    """Velocity PI / force-loop / mechanics of one axis (paper Fig. 3; docs/howto/machine-files.md).

    Friction ``Ffr(v) = Fc*s + (Fs - Fc)*exp(-(v/vs)^2)*s + B*v`` with
    ``s = tanh(v / friction_smoothing_m_s)``.
    """

    mass_kg: _in("mass_kg")
    coulomb_n: _in("coulomb_n")
    static_n: _in("static_n")
    stribeck_m_s: _in("stribeck_m_s")
    viscous_n_s_m: _in("viscous_n_s_m")
    kv_n_s_m: _in("kv_n_s_m")
    tn_s: _in("tn_s")
    force_lag_s: _in("force_lag_s")
    force_limit_n: _in("force_limit_n")
    friction_smoothing_m_s: _in("friction_smoothing_m_s") = 1e-4

    @model_validator(mode="after")
    def _static_above_coulomb(self) -> "Cascade":
        if self.static_n < self.coulomb_n:
            raise ValueError("static_n (Stribeck peak) must be >= coulomb_n")
        return self


Coef = _in("arx_coefficient")
_ORDER = MACHINE_FIELD_RANGES["arx_order"]


class Arx(_Frozen):
    """Identified discrete velocity loop of one axis (period Te), with friction and load.

    ``V(z) = (num[0] + num[1] z^-1 + ...) / (den[0] + den[1] z^-1 + ...)`` maps the
    velocity command (m/s) to the axis velocity (m/s); leading zeros of ``num``
    carry the loop's own delay. The position integrates the velocity of the last
    period: ``p_{k+1} = p_k + Te v_k``.

    Friction and an external load act as an input-equivalent velocity disturbance
    (the velocity command that would cancel them), subtracted from the command::

        u_eff = u - coulomb_m_s tanh(v / friction_smoothing_m_s) - viscous_ratio v
                  - load_m_s_per_n F_load

    with ``v`` the velocity of the last period (m/s) and ``F_load`` the load (N,
    opposing positive motion).
    """

    num: Annotated[tuple[Coef, ...], Field(min_length=_ORDER[0], max_length=_ORDER[1])]
    den: Annotated[tuple[Coef, ...], Field(min_length=_ORDER[0], max_length=_ORDER[1])]
    coulomb_m_s: _in("coulomb_m_s") = 0.0
    viscous_ratio: _in("viscous_ratio") = 0.0
    friction_smoothing_m_s: _in("friction_smoothing_m_s") = 1e-4
    load_m_s_per_n: _in("load_m_s_per_n") = 0.0

    @field_validator("den")
    @classmethod
    def _den_stable(cls, den: tuple[float, ...]) -> tuple[float, ...]:
        if den[0] != 1.0:
            raise ValueError(f"leading coefficient must be 1 (normalised), got {den[0]}")
        poles = np.roots(den) if len(den) > 1 else np.zeros(0)
        if poles.size and np.max(np.abs(poles)) >= 1.0:
            raise ValueError(
                f"the velocity loop must be stable; a pole has modulus {np.max(np.abs(poles)):.6g}"
            )
        return den

    @field_validator("num")
    @classmethod
    def _num_not_zero(cls, num: tuple[float, ...]) -> tuple[float, ...]:
        if sum(num) == 0.0:
            raise ValueError("the DC gain (sum of the coefficients) must not be zero")
        return num


Factor = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class Uncertainty(_Frozen):
    """How far a cascade axis may differ from its nominal values: per parameter a
    ``(low, high)`` factor on the nominal value (``low <= 1 <= high``; +-50 % is
    ``(0.5, 1.5)``, x0.5-x2 is ``(0.5, 2.0)``), and the extra dead time, ``(low, high)``
    whole samples added to the axis's dead time. Each field is named after the
    cascade field it scales. ``oga identify`` writes it from its confidence intervals and the
    evidence of model error, and says so: ``fit_status`` (``ok``, ``model-error``: the set
    widened by the evidence, ``poor``: the model does not cover the plant) and
    ``model_error_share`` (:class:`oga.identify.fit.AxisFit`); both absent from an assumed
    set (a preset's).
    """

    coulomb_n: tuple[Factor, Factor] = (1.0, 1.0)
    static_n: tuple[Factor, Factor] = (1.0, 1.0)
    mass_kg: tuple[Factor, Factor] = (1.0, 1.0)
    kv_n_s_m: tuple[Factor, Factor] = (1.0, 1.0)
    tn_s: tuple[Factor, Factor] = (1.0, 1.0)
    force_lag_s: tuple[Factor, Factor] = (1.0, 1.0)
    stribeck_m_s: tuple[Factor, Factor] = (1.0, 1.0)
    viscous_n_s_m: tuple[Factor, Factor] = (1.0, 1.0)
    dead_time_extra_samples: tuple[
        Annotated[int, Field(ge=0, le=10)], Annotated[int, Field(ge=0, le=10)]
    ] = (0, 0)
    fit_status: Literal["ok", "model-error", "poor"] | None = None
    model_error_share: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None

    @model_validator(mode="after")
    def _around_nominal(self) -> "Uncertainty":
        for name in FACTOR_FIELDS:
            lo, hi = getattr(self, name)
            if not lo <= 1.0 <= hi:
                raise ValueError(f"{name}: factors ({lo}, {hi}) must satisfy low <= 1 <= high")
        lo, hi = self.dead_time_extra_samples
        if lo > hi:
            raise ValueError(f"dead_time_extra_samples: lower end {lo} is above upper end {hi}")
        return self


#: The fields of :class:`Uncertainty` that are factors on a cascade field of that name.
FACTOR_FIELDS: tuple[str, ...] = (
    "coulomb_n", "static_n", "mass_kg", "kv_n_s_m", "tn_s", "force_lag_s", "stribeck_m_s",
    "viscous_n_s_m",
)


class Axis(_Frozen):
    """One linear axis: its limits, exactly one model kind, ``cascade`` or ``arx``, and,
    for a cascade, optionally its :class:`Uncertainty`.

    ``dead_time_samples`` (optional) is the axis's own dead time, position-loop samples
    between the velocity command and the velocity loop; unset, the axis has the machine's
    ``timing.dead_time_samples`` (:meth:`Machine.dead_time_samples_of`). A whole number, or
    a fraction where the command reaches the loop between two samples: ``2.4`` is two
    samples and four tenths of one (the simulation takes the command of that period as
    ``0.6 u[k-2] + 0.4 u[k-3]``, the linear-interpolation fractional delay; ``oga identify``
    writes one where it fits measurably better than a whole number).
    """

    limits: Limits
    cascade: Cascade | None = None
    arx: Arx | None = None
    uncertainty: Uncertainty | None = None
    dead_time_samples: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> "Axis":
        if (self.cascade is None) == (self.arx is None):
            raise ValueError("give exactly one axis model: a cascade table or an arx table")
        if self.uncertainty is not None and self.cascade is None:
            raise ValueError("uncertainty: only a cascade axis takes one")
        return self

    @property
    def kind(self) -> str:
        """The model kind: ``"cascade"`` or ``"arx"``."""
        return "cascade" if self.cascade is not None else "arx"


class Timing(_Frozen):
    """Loop timing: position-loop period, inner sub-steps, dead time; and one simulation setting.

    ``friction_linear_below_m_s`` (optional, unset by default: the exact kernel) lets the
    simulation take a cascade axis's friction force ``F_n(v)`` as its tangent at rest,
    ``Fs / friction_smoothing_m_s * v``, over the periods whose velocity provably stays below
    it at every sub-step (:mod:`oga.model.simulate`: the periods of an axis standing still then cost
    one linear map instead of the sub-steps). There ``|F_n - tangent| <= Fs x^3 / 3 +
    (Fs - Fc) (V / vs)^2 x`` with ``x = V / friction_smoothing_m_s``. The scenario plants of
    the robust search set it (:data:`oga.defaults.ROBUST_FRICTION_LINEAR_BELOW_M_S`); unset,
    it leaves the machine's digest as it was.
    """

    te_s: Annotated[float, Field(ge=DT_RANGE_S[0], le=DT_RANGE_S[1], allow_inf_nan=False)] = 0.001
    substeps: Annotated[int, Field(ge=1, le=1000)] = 8
    dead_time_samples: Annotated[int, Field(ge=0, le=100)] = 2
    friction_linear_below_m_s: _in("friction_linear_below_m_s") | None = None


class GainSettings(_Frozen):
    """Where gains may go: the Kp grid, its configured bounds, Kf grid, margins."""

    kp_span_m_min_per_mm: tuple[_in("kp_m_min_per_mm"), _in("kp_m_min_per_mm")] = (0.5, 5.0)
    kp_bounds_m_min_per_mm: tuple[_in("kp_m_min_per_mm"), _in("kp_m_min_per_mm")] = (1.0, 5.0)
    kp_step_m_min_per_mm: _in("kp_step_m_min_per_mm") = 0.1
    kf_range: tuple[_in("kf"), _in("kf")] = (0.0, 1.0)
    kf_step: _in("kf_step") = 0.1
    pm_min_deg: Annotated[float, Field(gt=0, lt=180)] = 70.0
    gm_min_db: _in("gm_min_db") = 10.0

    @model_validator(mode="after")
    def _ordered(self) -> "GainSettings":
        for name in ("kp_span_m_min_per_mm", "kp_bounds_m_min_per_mm", "kf_range"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: lower end {lo} is above upper end {hi}")
        return self


class PlannerSettings(_Frozen):
    """Share of each axis limit the interpolator plans with.

    The position loop's velocity command overshoots the setpoints' acceleration
    and jerk (by about 10-20 % at the usual gains), and the command must meet the
    axis limits too (paper eq. 2); the interpolator therefore keeps a reserve.
    Velocity is planned at the full limit.
    """

    accel_fraction: Annotated[float, Field(gt=0, le=1)] = 0.9
    jerk_fraction: Annotated[float, Field(gt=0, le=1)] = 0.75


Position = tuple[_in("position_mm"), _in("position_mm"), _in("position_mm")]


class WorkOffsets(_Frozen):
    """Work offsets G54 .. G59.3 (x, y, z machine coordinates of the work zero), mm; the ones
    not given are zero (LinuxCNC's parameters 5221.. without a parameter file)."""

    g54: Position = (0.0, 0.0, 0.0)
    g55: Position = (0.0, 0.0, 0.0)
    g56: Position = (0.0, 0.0, 0.0)
    g57: Position = (0.0, 0.0, 0.0)
    g58: Position = (0.0, 0.0, 0.0)
    g59: Position = (0.0, 0.0, 0.0)
    g59_1: Position = (0.0, 0.0, 0.0)
    g59_2: Position = (0.0, 0.0, 0.0)
    g59_3: Position = (0.0, 0.0, 0.0)


class Home(_Frozen):
    """Where a program's machine-position moves go, for the G-code readers (section
    ``[home]`` of a machine file; optional). Machine coordinates (x, y, z), mm.

    ``g28_mm`` / ``g30_mm``: the G28 / G30 positions (LinuxCNC's parameters 5161-5163 and
    5181-5183; default machine zero, LinuxCNC's without a parameter file);
    ``work_offsets_mm``: G54-G59.3.
    """

    g28_mm: Position = (0.0, 0.0, 0.0)
    g30_mm: Position = (0.0, 0.0, 0.0)
    work_offsets_mm: WorkOffsets = WorkOffsets()


class Machine(_Frozen):
    """A machine tool: named linear axes (subset of x, y, z), timing and gain settings.

    ``timing`` also holds the one simulation setting (not a property of the machine):
    ``timing.friction_linear_below_m_s``, the velocity below which the simulation may take
    the friction as linear (:class:`Timing`); unset (the default) the kernel is exact.
    """

    name: Annotated[str, Field(min_length=1, max_length=100)]
    source: str = Field("", description="Where the numbers come from.")
    axes: dict[str, Axis]
    timing: Timing = Timing()
    gains: GainSettings = GainSettings()
    planner: PlannerSettings = PlannerSettings()
    home: Home | None = None

    @model_validator(mode="after")
    def _axis_names(self) -> "Machine":
        bad = sorted(set(self.axes) - {"x", "y", "z"})
        if bad:
            raise ValueError(f"axes: unknown axis name(s) {bad}; use x, y, z")
        if not self.axes:
            raise ValueError("axes: at least one axis is required")
        v_lin = self.timing.friction_linear_below_m_s
        for name, ax in self.axes.items():
            cas = ax.cascade
            if v_lin is None or cas is None:
                continue
            for field in ("friction_smoothing_m_s", "stribeck_m_s"):
                if v_lin > FRICTION_LINEAR_MAX_SHARE * getattr(cas, field) * (1 + 1e-12):
                    raise ValueError(
                        f"timing.friction_linear_below_m_s: {v_lin} m/s is above "
                        f"{FRICTION_LINEAR_MAX_SHARE} of axes.{name}.cascade.{field} "
                        f"({getattr(cas, field)} m/s): the friction is not linear there")
        return self

    @property
    def te(self) -> float:
        """Position-loop period in seconds."""
        return self.timing.te_s

    def dead_time_samples_of(self, axis: str) -> float:
        """Dead time of ``axis``, position-loop samples: the axis's own
        ``dead_time_samples`` where it sets one, else ``timing.dead_time_samples``
        (MachineError if the machine lacks the axis)."""
        own = self.axis(axis).dead_time_samples
        return float(self.timing.dead_time_samples if own is None else own)

    def axis(self, name: str) -> Axis:
        """The axis called ``name`` (MachineError if the machine lacks it)."""
        try:
            return self.axes[name]
        except KeyError:
            raise MachineError(f"machine {self.name!r} has no axis {name!r}") from None

    def axis_limits(self) -> "AxisLimits":
        """Per-axis (x, y, z) kinematic limits for the planner and the checks.

        Axes the machine lacks get limit 0 (they must not move). Memoised on the machine
        (:func:`machine_memo`): every replay's checks ask for them.
        """
        return machine_memo(self, "axis_limits", self._axis_limits)

    def _axis_limits(self) -> "AxisLimits":
        """:meth:`axis_limits`, computed (read-only arrays in a frozen dataclass)."""
        from feedplan.limits import AxisLimits

        rows = [
            (a.limits.vmax_m_s, a.limits.amax_m_s2, a.limits.jmax_m_s3) if a else (0.0, 0.0, 0.0)
            for a in (self.axes.get(n) for n in ("x", "y", "z"))
        ]
        v, acc, j = zip(*rows)
        return AxisLimits(vmax_m_s=v, amax_m_s2=acc, jmax_m_s3=j)

    def ferror_limits(self) -> np.ndarray:
        """Per-axis (x, y, z) following-error limit, m; ``inf`` where none is set.

        Returns
        -------
        ndarray, shape (3,)
        """
        return np.array([
            a.limits.ferror_max_m if a is not None and a.limits.ferror_max_m is not None
            else np.inf
            for a in (self.axes.get(n) for n in ("x", "y", "z"))
        ])

    def planning_limits(self) -> "AxisLimits":
        """The limits the interpolator plans with: :meth:`axis_limits` times the planner fractions."""
        from feedplan.limits import AxisLimits

        lim = self.axis_limits()
        return AxisLimits(
            vmax_m_s=lim.vmax_m_s,
            amax_m_s2=lim.amax_m_s2 * self.planner.accel_fraction,
            jmax_m_s3=lim.jmax_m_s3 * self.planner.jerk_fraction,
        )

    def gcode_setup(self, tool_table: str | None = None):
        """The :class:`feedplan.gcode.Setup` of the G-code readers: :attr:`home` (machine
        zero and no offsets without it) and the tool table ``tool_table`` (its text, or
        None). GcodeError (line, column) if the table does not read."""
        from feedplan.gcode.setup import Setup, parse_tool_table

        tools = None if tool_table is None else parse_tool_table(tool_table, "tool table")
        home = self.home or Home()
        w = home.work_offsets_mm
        return Setup(
            g28_m=np.array(home.g28_mm) * 1e-3, g30_m=np.array(home.g30_mm) * 1e-3,
            work_offsets_m=np.array([getattr(w, f) for f in WorkOffsets.model_fields]) * 1e-3,
            tools=tools)

    def digest(self) -> str:
        """SHA-256 of the canonical JSON of this machine (identifies it in a table).

        Memoised on the machine (:func:`machine_memo`): every replay keys its packed parameters
        by it."""
        # without the unset model kind (an axis has exactly one)
        return machine_memo(self, "digest",
                        lambda: json_digest(self.model_dump(mode="json", exclude_none=True)))


#: What :func:`machine_memo` keeps, by ``id`` of the machine, while the machine lives.
_MACHINE_MEMOS: dict[int, dict] = {}


def machine_memo(machine: Machine, name: str, compute):
    """``compute()``, kept for ``machine`` under ``name`` until the machine is collected.

    A Machine is frozen, so what depends on it alone can be kept. Not on the instance: a
    ``model_copy(update=...)`` copies the instance's ``__dict__`` (and would carry a stale
    value); an ``id`` is not reused while the machine lives, and the entry goes with it
    (``weakref.finalize``).
    """
    key = id(machine)
    memo = _MACHINE_MEMOS.get(key)
    if memo is None:
        memo = _MACHINE_MEMOS[key] = {}
        weakref.finalize(machine, _MACHINE_MEMOS.pop, key, None)
    try:
        return memo[name]
    except KeyError:
        value = memo[name] = compute()
        return value


def json_digest(data) -> str:
    """SHA-256 (hex) of the canonical JSON of ``data`` (sorted keys, no spaces).

    Parameters
    ----------
    data : JSON-serialisable object
        E.g. a ``model_dump(mode="json")``.

    Returns
    -------
    str
        64 hex digits.
    """
    blob = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()


def _format_validation(err: ValidationError, where: str) -> str:
    parts = []
    for e in err.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "(root)"
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown field"
        parts.append(f"{loc}: {msg}")
    return f"{where}: " + "; ".join(parts)


def machine_from_dict(data: dict, where: str = "machine") -> Machine:
    """Validate a plain dict into a :class:`Machine`, raising MachineError naming the field."""
    if not isinstance(data, dict):
        raise MachineError(f"{where}: expected an object/table, got {type(data).__name__}")
    try:
        return Machine.model_validate(data)
    except ValidationError as err:
        raise MachineError(_format_validation(err, where)) from None


def load_machine(spec: str | FilePath) -> Machine:
    """A preset by name (``"ucp710"``) or a machine file (``.toml`` or ``.json``).

    Raises
    ------
    MachineError
        Unknown preset, unreadable file, or invalid content (field named).
    """
    text_spec = str(spec)
    if text_spec in PRESETS:
        path = _PRESET_DIR / f"{text_spec}.toml"
    else:
        path = FilePath(text_spec)
        if path.suffix.lower() not in (".toml", ".json"):
            raise MachineError(
                f"unknown machine {text_spec!r}: not a preset ({', '.join(PRESETS)}) "
                "nor a .toml/.json machine file"
            )
    raw = read_limited(path, MACHINE_MAX_BYTES, MachineError, "machine file")
    try:
        if path.suffix.lower() == ".toml":
            data = tomllib.loads(raw.decode("utf-8"))
        else:
            data = json.loads(raw)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise MachineError(f"{path.name}: not valid {path.suffix[1:].upper()}: {err}") from None
    return machine_from_dict(data, where=path.name)
