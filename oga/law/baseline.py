"""The fixed gains a law is judged against: the robust baseline of its programs.

:func:`program_baseline` calls the robust search's own baseline
(:func:`oga.search.robust.baseline.robust_baseline`, with the arguments
:func:`oga.search.robust.search.robust_optimize` gives it: the equal fixed gains of least
geometric-mean MSE(CE) over the set's objective plants among those that keep eq. 2, the
following-error limit and the stable range on every plant of the set and the nominal one),
found on the program at 100 % feed and replayed at every override.

A law for several programs is judged against their **joint** baseline
(:func:`joint_program_baseline`): the one pair of equal fixed gains that keeps every plant's
checks on every program, of least geometric-mean MSE(CE) over all of them. That is what the
machine runs without the law: one fixed setting for every part (each program's own
baseline would be a gain change per program, a schedule of its own). Judged against eight
different baselines (Kp 1.23 on line-contouring-xz to 2.0 on short_segments), one law for the
eight benchmark programs was certified in no round.
"""

from __future__ import annotations

from feedplan.setpoints import AXES, Setpoints
from oga.errors import OptionError
from oga.model.machine import Machine
from oga.search.robust.baseline import (BaselineResult, common_kp_range, joint_baseline,
                                        robust_baseline)
from oga.search.robust.plants import ScenarioSet

__all__ = ["program_baseline", "joint_program_baseline"]


def program_baseline(name: str, setpoints: Setpoints, machine: Machine, scenarios: ScenarioSet,
                     bounds, *, threads: int | None = None) -> BaselineResult:
    """The robust baseline of program ``name`` (``setpoints`` at 100 % feed) on
    ``machine``'s set (module doc); ``bounds`` its :func:`oga.verify.certificate.plant_bounds`.

    Raises
    ------
    OptionError
        No equal fixed gains keep the limits on every plant (the robust baseline's message,
        naming the program and the remedies).
    """
    moving = tuple(AXES[i] for i in setpoints.moving_axes)
    base = robust_baseline(setpoints, machine, scenarios, tuple(bounds),
                           common_kp_range(machine, bounds, moving), threads=threads)
    if not base.ok:
        raise OptionError(f"{name}: {base.message} (a law is certified on the set: "
                          "oga law has no nominal mode)")
    return base


def joint_program_baseline(setpoints: dict[str, Setpoints], machine: Machine,
                           scenarios: ScenarioSet, bounds, *, threads: int | None = None
                           ) -> dict[str, BaselineResult]:
    """The joint robust baseline of the programs ``setpoints`` (each at 100 % feed, by name)
    on ``machine``'s set (module doc); ``bounds`` the plants'
    :func:`oga.verify.certificate.plant_bounds` over every axis any program moves. Returns
    each program's :class:`BaselineResult` (the same gains).

    Raises
    ------
    OptionError
        No equal fixed gains keep the limits on every plant for every program.
    """
    found = joint_baseline(setpoints, machine, scenarios, tuple(bounds), threads=threads)
    if not found[0].ok:
        raise OptionError(f"{', '.join(setpoints)} together: {found[0].message} (one law for "
                          "several programs is judged against the one fixed setting that keeps "
                          "every plant's limits on all of them: leave out the program named, "
                          "or make a law per program)")
    return dict(zip(setpoints, found))
