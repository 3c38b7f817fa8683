"""The fixed gains a law is judged against: the robust baseline of each program.

One function, :func:`robust_baseline`, so that the law follows the robust search's baseline
wherever it is defined. Today it is the robust search's own
(:func:`oga.robust.search.robust_optimize`, step 2: the best equal fixed gains of a design
machine whose limit reserve is cut until they keep eq. 2, the following-error limit and
the stable range on every plant of the set), found on the program at 100 % feed and replayed
at every override.
"""

from __future__ import annotations

from dataclasses import dataclass

from feedplan.setpoints import AXES, Setpoints
from oga.machine import Machine
from oga.robust.certificate import plant_bounds
from oga.robust.plants import ScenarioSet, perturbed_machine
from oga.robust.search import _robust_baseline
from oga.verify import Verification

__all__ = ["Baseline", "robust_baseline", "common_kp_range"]


@dataclass(frozen=True, eq=False)
class Baseline:
    """A program's robust baseline.

    Attributes
    ----------
    kp_m_min_per_mm, kf : float
        The equal fixed gains of every moving axis.
    reserve : float
        The limit reserve of the design machine they were found on.
    replays : tuple of Verification
        Their replays on every plant of the set (the program at 100 % feed).
    """

    kp_m_min_per_mm: float
    kf: float
    reserve: float
    replays: tuple[Verification, ...]


def common_kp_range(machine: Machine, scenarios: ScenarioSet, bounds, axes) -> tuple[float, float]:
    """The Kp range stable on every plant of ``scenarios`` (``bounds``: their
    :func:`oga.robust.certificate.plant_bounds`) and on the nominal plant, over ``axes``,
    (m/min)/mm (as the robust search takes it)."""
    nominal = perturbed_machine(machine, {}, 0, machine.name)
    nb = plant_bounds(ScenarioSet(status="nominal-only", nominal=machine, plants=(nominal,),
                                  labels=("nominal",), draws=(({}, 0),), seed=0,
                                  n_monte_carlo=0, n_corners=0), axes)[0]
    every = tuple(bounds) + (nb,)
    return (max(b[a][0] for b in every for a in axes), min(b[a][1] for b in every for a in axes))


def robust_baseline(setpoints: Setpoints, machine: Machine, scenarios: ScenarioSet,
                    bounds) -> Baseline:
    """The robust baseline of ``setpoints`` on ``machine``'s set (module doc).

    Raises
    ------
    OptionError
        No equal fixed gains keep the limits on every plant (the robust search's message).
    """
    moving = tuple(AXES[i] for i in setpoints.moving_axes)
    kp_range = common_kp_range(machine, scenarios, bounds, moving)
    kp, kf, reserve, replays = _robust_baseline(setpoints, machine, scenarios, bounds, kp_range)
    return Baseline(kp_m_min_per_mm=float(kp), kf=float(kf), reserve=float(reserve),
                    replays=tuple(replays))
