"""Options of the gain search: one pydantic model for library, CLI and API.

Field names are the CLI flags of ``oga optimize`` (``np``, ``lam``, ``adjust``,
``gains``, ``baseline``, ``kp_range``, ``nominal``, ``certify``, ``threads``, ``feed``,
``tolerance``, ``reader``; ``tool_table`` holds the text of the ``--tool-table`` file);
unknown keys are refused. Defaults come from :mod:`oga.defaults`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import (BaseModel, ConfigDict, Field, StrictBool, ValidationError, field_validator,
                      model_validator)

from oga import defaults
from oga.errors import OptionError
from oga.parallel import MAX_THREADS

__all__ = ["OptimizeOptions", "options_from_dict"]

Finite = Annotated[float, Field(allow_inf_nan=False)]


class OptimizeOptions(BaseModel):
    """What to optimise and how.

    Attributes
    ----------
    mode : {"full", "paper"}
        ``"full"``: the gain trajectory over a window is planned by sequential
        QP on the exact model, partly applied, and planned again as the window
        recedes (:mod:`oga.search.window`); ``"paper"``: the published method, five candidate
        increments per gain and sample, each held over the horizon
        (:mod:`oga.search.paper`).
    baseline : "best" or (kp_m_min_per_mm, kf)
        The fixed gains the schedule starts from and is compared with: ``"best"``
        (the best equal fixed gains of the ranges stage) or one explicit pair
        applied to every axis.
    adjust : tuple of axis names, or None
        Axes whose gains the search adjusts; None = every contouring (moving) axis.
        The others keep the baseline gains.
    gains : tuple of "kp", "kf"
        Which gains move.
    kp_range : (lo, hi) in (m/min)/mm, or None
        Bounds of the adjusted Kp; None = each axis's stable range. Must lie
        inside the stable range.
    np : int or None
        Prediction horizon in samples (full mode: the window planned at once);
        None: the mode's default (:data:`oga.defaults.NP`).
    knot : int or None
        Full mode: samples between the control points of the planned gain trajectory;
        None: ``max(MPC_KNOT_SAMPLES, np // MPC_WINDOW_INTERVALS)`` of
        :mod:`oga.defaults` (20 at the default window). Finer knots on a long window
        follow faster gain changes, at a cost growing with the square of their number.
    lam : float or None
        Weight of the gain increments in the cost ``J = E'E + lam dK'dK`` with the
        contour error E in mm in paper mode (the paper's unit) and in um in full
        mode, and the increments in (m/min)/mm (Kp) and 1 (Kf); None: the mode's
        default (:data:`oga.defaults.LAMBDA`).
    anchor : float or None
        Weight of the gains' distance from the baseline in the cost,
        ``+ anchor (K - K_baseline)'(K - K_baseline)`` (E'E's unit per unit^2); 0 is
        the paper's cost. On straight moves the contour error does not see the
        axes' lag, so without it the gains drift there unchecked, and the jerk
        limit then keeps them from coming back in time for the next curve.
        None: the mode's default (:data:`oga.defaults.ANCHOR`); the robust search then
        tries :data:`oga.defaults.ROBUST_ANCHOR_RETRY` where no table passes at the default
        (its result's options name the anchor kept).
    nominal : bool
        True: search the machine's nominal model only (bit-identical to the search before
        the robust one). False (:data:`oga.defaults.NOMINAL`): where the machine has an
        uncertainty set, the robust search (:mod:`oga.search.robust`) and its certificate; a
        machine without a set is searched nominally either way.
    certify : int or None
        Robust search: the Monte Carlo plants of the certificate's set (its corners come on
        top); None: :data:`oga.defaults.ROBUST_MC_PLANTS`. More plants tighten the
        certificate's confidence bound (:mod:`oga.verify.certificate`) and cost time.
    threads : int or None
        Threads for the independent work of a search (the certificate's replays, the set's
        stable ranges, the baseline's candidates; the window search runs on one: its windows
        follow each other); None: the cores this process may
        use (the service and ``oga batch`` run each job on one unless set). The result does
        not depend on it, to the last bit.
    feed_mm_per_min : float or None
        Overrides the program's feed.
    tolerance_mm : float
        Interpolation tolerance of the feed planner.
    reader : {"auto", "builtin", "linuxcnc"}
        The G-code reader (:func:`feedplan.gcode.parse_gcode`): the built-in one, LinuxCNC's
        interpreter, or the built-in one and LinuxCNC's where it refuses (the default).
    tool_table : str or None
        A LinuxCNC tool table (its text; lengths in mm) for G43's tool lengths; None: no
        table (G43 applies length 0, with a warning).
    """

    model_config = ConfigDict(frozen=True, extra="forbid", populate_by_name=True)

    mode: Literal["full", "paper"] = "full"
    baseline: Literal["best"] | tuple[Finite, Finite] = "best"
    adjust: tuple[Literal["x", "y", "z"], ...] | None = None
    gains: tuple[Literal["kp", "kf"], ...] = ("kp", "kf")
    kp_range: tuple[Finite, Finite] | None = None
    np: Annotated[int, Field(ge=1, le=1000)] | None = Field(
        None, json_schema_extra={"default_per_mode": defaults.NP}
    )
    knot: Annotated[int, Field(ge=2, le=1000)] | None = None
    lam: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None
    anchor: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None
    nominal: StrictBool = defaults.NOMINAL
    certify: Annotated[int, Field(ge=1, le=defaults.ROBUST_MC_PLANTS_MAX)] | None = None
    threads: Annotated[int, Field(ge=1, le=MAX_THREADS)] | None = None
    feed_mm_per_min: Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] | None = Field(
        None, alias="feed"
    )
    tolerance_mm: Annotated[float, Field(ge=round(defaults.TOL_RANGE_M[0] * 1e3, 9),
                                         le=round(defaults.TOL_RANGE_M[1] * 1e3, 9),
                                         allow_inf_nan=False)] = Field(
        defaults.TOL_M * 1e3, alias="tolerance"
    )

    reader: Literal["auto", "builtin", "linuxcnc"] = defaults.GCODE_READER
    tool_table: Annotated[str, Field(max_length=1 << 20)] | None = None

    @field_validator("tool_table")
    @classmethod
    def _tools(cls, v):
        if v is not None:
            from feedplan.gcode.setup import parse_tool_table

            parse_tool_table(v)  # GcodeError (a ValueError) naming the line and column
        return v

    @field_validator("adjust", "gains", mode="before")
    @classmethod
    def _split(cls, v):
        if isinstance(v, str):
            v = tuple(p.strip() for p in v.split(",") if p.strip())
        return v

    @field_validator("baseline", "kp_range", mode="before")
    @classmethod
    def _pair(cls, v, info):
        if isinstance(v, str) and v != "best":
            try:
                v = tuple(float(p) for p in v.split(","))
            except ValueError:
                v = ()
            if len(v) != 2:
                raise ValueError("expected two numbers LO,HI" if info.field_name == "kp_range"
                                 else "expected 'best' or two numbers KP,KF")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> "OptimizeOptions":
        if not self.gains:
            raise ValueError("gains: name at least one of kp, kf")
        if len(set(self.gains)) != len(self.gains):
            raise ValueError("gains: repeated entry")
        if self.adjust is not None and (not self.adjust or len(set(self.adjust)) != len(self.adjust)):
            raise ValueError("adjust: name each axis once (x, y, z)")
        if self.baseline != "best":
            kp, kf = self.baseline
            if kp <= 0:
                raise ValueError("baseline: Kp must be positive")
            if not 0 <= kf <= 1:
                raise ValueError("baseline: Kf must lie in [0, 1]")
        if self.knot is not None and self.mode != "full":
            raise ValueError("knot: only full mode plans a spline of gains")
        if self.nominal and self.certify is not None:
            raise ValueError("certify: the nominal search has no certificate (drop nominal)")
        if self.kp_range is not None:
            lo, hi = self.kp_range
            if not 0 < lo <= hi:
                raise ValueError("kp_range: need 0 < LO <= HI")
        return self

    @property
    def np_value(self) -> int:
        """``np``, or the mode's default."""
        return defaults.NP[self.mode] if self.np is None else self.np

    @property
    def knot_value(self) -> int:
        """``knot``, or the default spacing for the window ``np_value``."""
        if self.knot is not None:
            return self.knot
        return max(defaults.MPC_KNOT_SAMPLES, self.np_value // defaults.MPC_WINDOW_INTERVALS)

    @property
    def lam_value(self) -> float:
        """``lam``, or the mode's default."""
        return defaults.LAMBDA[self.mode] if self.lam is None else self.lam

    @property
    def anchor_value(self) -> float:
        """``anchor``, or the mode's default."""
        return defaults.ANCHOR[self.mode] if self.anchor is None else self.anchor

    @property
    def tol_m(self) -> float:
        """Interpolation tolerance in metres."""
        return self.tolerance_mm * 1e-3

    @property
    def feed_m_s(self) -> float | None:
        """Feed override in m/s (None: the program's feed)."""
        return None if self.feed_mm_per_min is None else self.feed_mm_per_min / 60e3

    def as_dict(self) -> dict:
        """Plain JSON-able dict with the CLI/API names, mode defaults filled in."""
        out = self.model_dump(mode="json", by_alias=True)
        out["np"] = self.np_value
        out["lam"] = self.lam_value
        out["anchor"] = self.anchor_value
        return out


def options_from_dict(data: dict | None = None, *, names: dict[str, str] | None = None,
                      **overrides) -> OptimizeOptions:
    """Validate options (API body, CLI flags), raising OptionError naming the field.

    ``names`` maps a field to the name the caller gave it (the CLI: its flag); such a
    field's message also quotes the value given.
    """
    merged = {**(data or {}), **{k: v for k, v in overrides.items() if v is not None}}
    try:
        return OptimizeOptions.model_validate(merged)
    except ValidationError as err:
        parts = []
        for e in err.errors():
            loc = [str(x) for x in e["loc"]]
            msg = "unknown option" if e["type"] == "extra_forbidden" else e["msg"]
            msg = msg.removeprefix("Value error, ")
            head, sep, rest = msg.partition(": ")
            if not loc and sep and head in OptimizeOptions.model_fields:  # _consistent's
                loc, msg = [head], rest
            if names and loc and loc[0] in names:
                parts.append(f"{names[loc[0]]}: {msg} (got {merged.get(loc[0])!r})")
            else:
                parts.append(f"{'.'.join(loc) or 'options'}: {msg}")
        raise OptionError("; ".join(parts)) from None
