"""The certificate of a gain law: the robust certificate of a table, on every program the law
was made for and at every feed override.

For each program and override the law's gains at every sample (:func:`oga.law.law.law_gains`
on that plan) and the baseline (:mod:`oga.law.baseline`: the program's robust one, or the
programs' joint one for a law of several) are replayed from rest on every plant of the
machine's set, with the same replay and checks as a table's certificate
(:func:`oga.verify.certificate.certify`: paper eq. 2 on every sample, the following-error
limit, Kp inside each plant's own stable range): per case the MSE(CE) ratio's median, 90th
percentile and worst, and the plants where a replay breaks a check. The law passes when
every case passes (worst ratio <= 1, no plant where the law breaks a check the baseline
keeps): one law runs at whatever override the operator sets.

:func:`certify_law` screens first: the law on the set's corners and first
:data:`oga.defaults.ROBUST_SUBSET` Monte Carlo plants in every case; a case that fails
there fails on the whole set (its worst ratio and breaks are at least the screen's), so
the whole set is replayed only for a law that passes the screen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oga import defaults
from oga.verify.certificate import Certificate, certify
from oga.search.robust.plants import ScenarioSet
from oga.law.law import Law, law_gains
from oga.verify.replay import ReplayGains, verify_prepared

__all__ = ["LawCertificate", "certify_law"]


@dataclass(frozen=True, eq=False)
class LawCertificate:
    """A law's certificates, one per program and override.

    Attributes
    ----------
    status : {"ok", "failed"}
    reasons : tuple of str
        Why it failed, naming the program and override (empty when ok).
    cases : dict of (str, float) to Certificate
        Per (program, override).
    plants : tuple of int
        The plants of the set replayed (all of them, or the screen's).
    full : bool
        Replayed on the whole set.
    """

    status: str
    reasons: tuple[str, ...]
    cases: dict[tuple[str, float], Certificate]
    plants: tuple[int, ...]
    full: bool

    @property
    def key(self) -> tuple:
        """Failed, plants where the law alone breaks a check (all cases), worst ratio."""
        return (self.status != "ok" or not self.full,
                sum(len(c.breaks("schedule-only")) for c in self.cases.values()),
                max(c.worst for c in self.cases.values()))

    def schedule_only_excess(self) -> float:
        """The largest limit ratio of the law's replays on the plants where it alone breaks a
        check (1.0 where there is none)."""
        worst = 1.0
        for c in self.cases.values():
            for p in c.plants:
                if p.schedule_only_break:
                    v = p.schedule
                    worst = max(worst, float(np.max(v.command_ratio)),
                                float(np.nanmax(np.append(v.ferror_ratio, 0.0))))
        return worst

    def worst_plants(self) -> list[int]:
        """Plants of the set (indices), the largest ratio over the cases first."""
        worst: dict[int, float] = {}
        for c in self.cases.values():
            for i, r in zip(self.plants, c.ratio):
                worst[i] = max(worst.get(i, 0.0), float(r))
        return sorted(worst, key=lambda i: -worst[i])

    def summary(self) -> dict:
        """Per case the certificate's figures (:meth:`Certificate.summary` without the
        per-plant ratios), for the summary JSON."""
        out = []
        for (prog, o), c in self.cases.items():
            s = c.summary()
            s.pop("ratio_per_plant", None)
            out.append({"program": prog, "override": o, **s})
        return {"status": self.status, "reasons": list(self.reasons), "full_set": self.full,
                "cases": out}


def _subset(scenarios: ScenarioSet, keep) -> ScenarioSet:
    return ScenarioSet(status=scenarios.status, nominal=scenarios.nominal,
                       plants=tuple(scenarios.plants[i] for i in keep),
                       labels=tuple(scenarios.labels[i] for i in keep),
                       draws=tuple(scenarios.draws[i] for i in keep), seed=scenarios.seed,
                       n_monte_carlo=sum(i < scenarios.n_monte_carlo for i in keep),
                       n_corners=sum(i >= scenarios.n_monte_carlo for i in keep))


def _screen(scenarios: ScenarioSet) -> tuple[int, ...]:
    return tuple(sorted({*range(min(defaults.ROBUST_SUBSET, scenarios.n_monte_carlo)),
                         *range(scenarios.n_monte_carlo, len(scenarios))}))


def _certify_on(law, cases, machine, scenarios, keep) -> LawCertificate:
    sub = _subset(scenarios, keep)
    out, reasons = {}, []
    for prog, o, sp, base, base_replays, bounds in cases:
        n = len(sp)
        bkp, bkf = np.full((n, 3), base.kp), np.full((n, 3), base.kf)
        missing = [i for i in keep if i not in base_replays]
        gains = ReplayGains.of(sp, bkp, bkf) if missing else None  # once, not per plant
        for i in missing:  # without series: certify replays its worst plant's
            base_replays[i] = verify_prepared(sp, scenarios.plants[i], gains, bounds[i],
                                              series=False)
        kp, kf = law_gains(law, sp)
        cert = certify(sp, machine, kp, kf, bkp, bkf, sub, tuple(bounds[i] for i in keep),
                       tuple(base_replays[i] for i in keep))
        out[(prog, o)] = cert
        reasons += [f"{prog} at {o * 100:g} % feed: {r}" for r in cert.reasons]
    return LawCertificate(status="failed" if reasons else "ok", reasons=tuple(reasons),
                          cases=out, plants=tuple(keep), full=len(keep) == len(scenarios))


def certify_law(law: Law, cases, machine, scenarios: ScenarioSet,
                screen: bool = True) -> LawCertificate:
    """Certify ``law`` on every case (module doc).

    Parameters
    ----------
    law : Law
    cases : list of tuple
        ``(program, override, setpoints, baseline, baseline_replays, bounds)``: the
        program's :class:`oga.search.robust.baseline.BaselineResult`, its replays by plant index (filled
        in here where missing) and the set's stable ranges over the program's moving axes
        (:func:`oga.verify.certificate.plant_bounds`).
    machine : Machine
    scenarios : ScenarioSet
    screen : bool
        Screen first (module doc); False replays the whole set at once.

    Returns
    -------
    LawCertificate
        On the whole set, or on the screen when the law fails there.
    """
    if screen:
        keep = _screen(scenarios)
        if len(keep) < len(scenarios):
            first = _certify_on(law, cases, machine, scenarios, keep)
            if first.status != "ok":
                return first
    return _certify_on(law, cases, machine, scenarios, tuple(range(len(scenarios))))
