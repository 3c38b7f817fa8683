"""The robustness certificate of a gain table: its replay on every plant of an uncertainty set.

On each plant of a :class:`oga.search.robust.plants.ScenarioSet` the schedule and the fixed
baseline are replayed from rest by :func:`oga.verify.verify` (the same replay and the
same checks as the nominal verification), with the plant's own stable Kp range as the
stability bound. Per plant: the ratio MSE(CE) schedule / baseline, the largest contour
and following errors, and whether each replay keeps the limits (eq. 2 and the
following-error limit) and the plant's stable range. Over the set: the ratio's median,
90th percentile and worst, and the plants where a replay breaks a check.

A certificate passes (status ``"ok"``) when the worst ratio is at most 1 and there is no
plant where the schedule breaks a check the baseline keeps on that plant.

**Confidence** (:meth:`Certificate.confidence`): the Monte Carlo plants are independent
draws from the set, so the share ``p`` of the set's machines where the table *fails*
(worse than the baseline, or breaking a check the baseline keeps) is bounded from the
``k`` failures among the ``n`` draws: the one-sided exact binomial (Clopper-Pearson) upper
bound at level ``L``, the ``p`` with ``P(X <= k | n, p) = 1 - L``, i.e. the ``L`` quantile of
``Beta(k + 1, n - k)`` (1 when ``k = n``); with no failure ``1 - (1 - L)^(1/n)``: 4.6 % for
64 draws at 95 %, under 1 % from 299. The corners are the set's extremes, not draws: they
are certified (every one must pass) but do not count in the bound.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import betaincinv

from feedplan.setpoints import AXES, Setpoints
from oga import defaults
from oga.errors import OptionError
from oga.model.machine import Machine
from oga.parallel import thread_map
from oga.search.robust.plants import ScenarioSet, scenario_set
from oga.model.stability import stable_ends
from oga.verify.replay import ReplayGains, Verification, verify_prepared

__all__ = ["PlantReplay", "Certificate", "share_bound", "confidence_text", "plant_bounds",
           "certify", "certify_result"]

_UM = 1e6
#: Plants replayed per thread between two progress reports of :func:`certify`.
_PROGRESS_BATCH = 4


@dataclass(frozen=True, eq=False)
class PlantReplay:
    """The schedule and the baseline on one plant.

    Attributes
    ----------
    label : str
        The plant (``"mc-0007"``, ``"corner ..."``).
    kp_bounds : dict
        The plant's stable Kp range per moving axis, (m/min)/mm.
    schedule, baseline : Verification
        The two replays; their ``pos``/``u``/``ce`` series only on the certificate's worst
        plant (:attr:`Certificate.worst_plant`), None on the others.
    """

    label: str
    kp_bounds: dict[str, tuple[float, float]]
    schedule: Verification
    baseline: Verification

    @property
    def ratio(self) -> float:
        """MSE(CE) of the schedule over MSE(CE) of the baseline on this plant."""
        return self.schedule.metrics.mse_m2 / self.baseline.metrics.mse_m2

    @property
    def schedule_only_break(self) -> bool:
        """The schedule breaks a check (limits or stability) that the baseline keeps."""
        return ((not self.schedule.limits_ok and self.baseline.limits_ok)
                or (not self.schedule.stability_ok and self.baseline.stability_ok))


@dataclass(frozen=True, eq=False)
class Certificate:
    """A schedule against the fixed baseline over a scenario set.

    Attributes
    ----------
    status : {"ok", "failed"}
        ``"ok"``: worst ratio <= 1 and no plant where the schedule alone breaks a check.
    reasons : tuple of str
        Why it failed, in words (empty when ok).
    scenarios : ScenarioSet
        The plants.
    plants : tuple of PlantReplay
        One per plant, in the set's order.
    ratio : ndarray, shape (P,)
        MSE ratio per plant.
    """

    status: str
    reasons: tuple[str, ...]
    scenarios: ScenarioSet
    plants: tuple[PlantReplay, ...]
    ratio: np.ndarray

    @property
    def median(self) -> float:
        """Median of the ratio over the plants."""
        return float(np.median(self.ratio))

    @property
    def p90(self) -> float:
        """90th percentile of the ratio (linear interpolation)."""
        return float(np.percentile(self.ratio, 90))

    @property
    def worst(self) -> float:
        """Largest ratio."""
        return float(self.ratio.max())

    @property
    def worst_plant(self) -> PlantReplay:
        """The plant of the largest ratio."""
        return self.plants[int(np.argmax(self.ratio))]

    def failures(self) -> np.ndarray:
        """Per plant, whether the schedule fails there: ratio above 1, or a check broken that
        the baseline keeps, shape (P,)."""
        return np.array([p.ratio > 1.0 or p.schedule_only_break for p in self.plants], dtype=bool)

    def confidence(self, level: float = defaults.ROBUST_CONFIDENCE) -> dict:
        """The upper confidence bound on the share of the set's machines where the schedule
        fails (module doc), from the Monte Carlo plants.

        Returns
        -------
        dict
            ``{"level", "draws", "failures", "share_bound"}``; ``share_bound`` is None when
            the set has no Monte Carlo plant.
        """
        n = self.scenarios.n_monte_carlo
        k = int(self.failures()[:n].sum())
        return {"level": level, "draws": n, "failures": k,
                "share_bound": share_bound(k, n, level) if n else None}

    def breaks(self, which: str) -> tuple[str, ...]:
        """Labels of the plants where a replay breaks a check.

        Parameters
        ----------
        which : {"schedule", "baseline", "schedule-only"}
            The schedule's breaks, the baseline's, or where the schedule breaks a check
            the baseline keeps.
        """
        if which == "schedule-only":
            return tuple(p.label for p in self.plants if p.schedule_only_break)
        if which not in ("schedule", "baseline"):
            raise OptionError(f"breaks: unknown replay {which!r}; use schedule, baseline or schedule-only")
        return tuple(p.label for p in self.plants if not getattr(p, which).ok)

    def summary(self) -> dict:
        """The certificate in users' units (um), for the summary JSON."""

        def largest(which: str) -> dict:
            vs = [getattr(p, which) for p in self.plants]
            return {
                "max_ce_um": max(v.metrics.max_abs_m for v in vs) * _UM,
                "track_max_um": {a: max(v.metrics.track_max_m[i] for v in vs) * _UM
                                 for i, a in enumerate(AXES)},
            }

        s = self.scenarios
        return {
            "status": self.status,
            "reasons": list(self.reasons),
            "plants": len(self.plants),
            "monte_carlo": s.n_monte_carlo,
            "corners": s.n_corners,
            "seed": s.seed,
            "ratio_median": self.median,
            "ratio_p90": self.p90,
            "ratio_worst": self.worst,
            "worst_plant": self.worst_plant.label,
            "breaks": {w: list(self.breaks(w)) for w in ("schedule", "baseline", "schedule-only")},
            "confidence": self.confidence(),
            "schedule": largest("schedule"),
            "baseline": largest("baseline"),
            "ratio_per_plant": {p.label: float(r) for p, r in zip(self.plants, self.ratio)},
        }


def share_bound(failures: int, draws: int, level: float = defaults.ROBUST_CONFIDENCE) -> float:
    """The one-sided exact binomial (Clopper-Pearson) upper bound, at ``level``, on a share
    of which ``failures`` of ``draws`` independent draws fell (module doc).

    Raises
    ------
    OptionError
        ``draws < 1``, ``failures`` outside ``0..draws`` or ``level`` outside (0, 1).
    """
    if draws < 1 or not 0 <= failures <= draws or not 0.0 < level < 1.0:
        raise OptionError(f"confidence bound: need 0 <= failures <= draws, draws >= 1 and a "
                          f"level in (0, 1), got {failures}, {draws}, {level}")
    if failures == draws:
        return 1.0
    return float(betaincinv(failures + 1, draws - failures, level))


def confidence_text(cert: dict) -> str:
    """A certificate summary's (:meth:`Certificate.summary`) confidence bound in words: the
    CLI's line, the report's caption."""
    c = cert["confidence"]
    if c["share_bound"] is None:
        return "no Monte Carlo plant: no confidence bound"
    table = "the table" if cert["status"] == "ok" else "the searched table (not exported)"
    return (f"at {c['level'] * 100:g} % confidence {table} fails (worse than the baseline, or a "
            f"check broken the baseline keeps) on at most {c['share_bound'] * 100:.2f} % of the "
            f"set's machines ({c['failures']} of {c['draws']} Monte Carlo plants fail)")


def plant_bounds(scenarios: ScenarioSet, axes, threads: int = 1
                 ) -> tuple[dict[str, tuple[float, float]], ...]:
    """Each plant's stable Kp range per axis of ``axes``, (m/min)/mm: the ends of
    :func:`oga.model.stability.stable_range`, by :func:`oga.model.stability.stable_ends` (compute once
    per set: a range costs a margin sweep), the plants on ``threads`` threads."""
    ends = thread_map(lambda plant: {a: tuple(float(k) for k in stable_ends(plant, a))
                                     for a in axes}, scenarios.plants, threads)
    return tuple(ends)


def certify(
    setpoints: Setpoints,
    machine: Machine,
    kp_m_min_per_mm: np.ndarray,
    kf: np.ndarray,
    baseline_kp_m_min_per_mm: np.ndarray,
    baseline_kf: np.ndarray,
    scenarios: ScenarioSet | None = None,
    bounds: tuple[dict[str, tuple[float, float]], ...] | None = None,
    baseline_replays: tuple[Verification, ...] | None = None,
    schedule_replays: dict[int, Verification] | None = None,
    progress: Callable[[float], None] | None = None,
    threads: int = 1,
) -> Certificate:
    """Replay a schedule and the fixed baseline on every plant of ``machine``'s set.

    Parameters
    ----------
    setpoints : Setpoints
        The planned motion (N samples).
    machine : Machine
        The nominal machine, with its uncertainty set.
    kp_m_min_per_mm, kf : ndarray, shape (N, 3)
        The schedule.
    baseline_kp_m_min_per_mm, baseline_kf : ndarray, shape (N, 3)
        The fixed baseline's gains per sample.
    scenarios : ScenarioSet, optional
        Default :func:`oga.search.robust.plants.scenario_set` of ``machine`` (its default count,
        seed and corners).
    bounds : tuple of dict, optional
        :func:`plant_bounds` of ``scenarios`` over the moving axes (computed when omitted).
    baseline_replays : tuple of Verification, optional
        The baseline's replays on ``scenarios`` (one per plant, with ``bounds``), when
        already made: a search certifying several tables against one baseline replays it once.
    schedule_replays : dict of int to Verification, optional
        The schedule's replays already made, by plant index in ``scenarios`` (with
        ``bounds``): a certificate that completes a screen of some plants reuses them.
    progress : callable, optional
        Called with the share of the plants replayed (0..1) after every few plants.
    threads : int
        Threads replaying the plants (the same certificate for any count).

    Returns
    -------
    Certificate
    """
    if scenarios is None:
        scenarios = scenario_set(machine)
    moving = tuple(AXES[i] for i in setpoints.moving_axes)
    if bounds is None:
        bounds = plant_bounds(scenarios, moving)

    # the tables' plant-independent work (checks, SI gains, largest steps) once, not per plant
    table = ReplayGains.of(setpoints, kp_m_min_per_mm, kf)
    base = (None if baseline_replays is not None
            else ReplayGains.of(setpoints, baseline_kp_m_min_per_mm, baseline_kf))

    def replay(i: int) -> PlantReplay:
        plant, bnd = scenarios.plants[i], bounds[i]
        return PlantReplay(
            label=scenarios.labels[i],
            kp_bounds=bnd,
            schedule=(schedule_replays[i] if schedule_replays and i in schedule_replays
                      else verify_prepared(setpoints, plant, table, bnd, series=False)),
            baseline=(verify_prepared(setpoints, plant, base, bnd, series=False)
                      if baseline_replays is None else baseline_replays[i]),
        )

    replays = _batched(replay, len(scenarios), progress, threads)
    _worst_with_series(setpoints, replays, scenarios, bounds, table, base,
                       (baseline_kp_m_min_per_mm, baseline_kf))
    return _verdict(replays, scenarios)


def _worst_with_series(setpoints, replays, scenarios, bounds, table, base, base_gains) -> None:
    """The worst plant's two replays in ``replays`` (changed in place) with their series (the
    report draws them), replayed again: the same figures, bit for bit. ``base``: the
    baseline's :class:`ReplayGains`, or None (prepared from ``base_gains`` (kp, kf) if
    needed)."""
    w = int(np.argmax([p.ratio for p in replays]))
    plant, bnd, worst = scenarios.plants[w], bounds[w], replays[w]
    if worst.schedule.pos is None:
        worst = replace(worst, schedule=verify_prepared(setpoints, plant, table, bnd))
    if worst.baseline.pos is None:
        if base is None:
            base = ReplayGains.of(setpoints, *base_gains)
        worst = replace(worst, baseline=verify_prepared(setpoints, plant, base, bnd))
    replays[w] = worst


def _batched(replay, n, progress, threads) -> list:
    """``replay(i)`` for ``i < n`` on ``threads`` threads, ``progress`` told the share done
    after every :data:`_PROGRESS_BATCH` plants per thread (all submitted at once: no thread
    waits for a batch's slowest replay)."""
    every = _PROGRESS_BATCH * threads

    def done(k: int) -> None:
        if progress is not None and (k % every == 0 or k == n):
            progress(k / n)
    return thread_map(replay, range(n), threads, done)


def _verdict(replays, scenarios) -> Certificate:
    """The :class:`Certificate` of the plants' ``replays``: failed where the schedule is worse
    than the baseline on a plant, or breaks a check there that the baseline keeps."""
    ratio = np.array([p.ratio for p in replays])
    reasons = []
    if ratio.max() > 1.0:
        worst = replays[int(np.argmax(ratio))]
        reasons.append(f"the schedule is worse than the fixed baseline on plant {worst.label!r} "
                       f"(MSE ratio {ratio.max():.3f})")
    only = [p.label for p in replays if p.schedule_only_break]
    if only:
        first = next(p for p in replays if p.schedule_only_break)
        reasons.append(f"the schedule breaks a check the baseline keeps on {len(only)} plant(s), "
                       f"first {first.label!r}: {first.schedule.violations[0]}")
    return Certificate(status="failed" if reasons else "ok", reasons=tuple(reasons),
                       scenarios=scenarios, plants=tuple(replays), ratio=ratio)


def certify_result(result, scenarios: ScenarioSet | None = None, threads: int = 1) -> Certificate:
    """:func:`certify` of an :class:`oga.optimize.OptimizeResult`'s searched schedule
    against its fixed baseline, on its machine's set (on ``threads`` threads)."""
    n = len(result.setpoints)
    base_kp = np.tile([result.baseline_kp[a] for a in AXES], (n, 1))
    base_kf = np.tile([result.baseline_kf[a] for a in AXES], (n, 1))
    s = result.searched_schedule
    return certify(result.setpoints, result.machine, s.kp_m_min_per_mm, s.kf, base_kp, base_kf,
                   scenarios, threads=threads)
