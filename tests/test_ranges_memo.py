"""The best fixed gains found with a memo shared across limit sets (design machines, their
limits cut reserve after reserve) are those of a fresh search, bit
for bit, whichever configurations the memo already knew."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from feedplan.read import load_toolpath
from oga.model.machine import load_machine
from oga.pipeline import plan_toolpath
from oga.search.ranges import EqualGainMemo, best_fixed_gains
from oga.model.machine import Machine, machine_from_dict

DATA = Path(__file__).parent / "data"
UCP = load_machine("ucp710")


def design_machine(machine: Machine, reserve: float, kp_bounds: tuple[float, float]) -> Machine:
    """``machine`` with acceleration, jerk and following-error limits times ``reserve`` and
    its configured Kp bounds cut to ``kp_bounds``; no uncertainty section."""
    data = machine.model_dump(mode="json", exclude_none=True)
    for ax in data["axes"].values():
        ax.pop("uncertainty", None)
        lim = ax["limits"]
        for k in ("amax_m_s2", "jmax_m_s3", "ferror_max_m"):
            if k in lim:
                lim[k] = lim[k] * reserve
    lo, hi = data["gains"]["kp_bounds_m_min_per_mm"]
    data["gains"]["kp_bounds_m_min_per_mm"] = [max(lo, kp_bounds[0]), min(hi, kp_bounds[1])]
    data["name"] = f"{machine.name}-design"
    return machine_from_dict(data, where="design machine")


def _same(a, b):
    if a is None or b is None:
        return a is None and b is None
    return (a.kp == b.kp and a.kf == b.kf and a.mse_ce_m2 == b.mse_ce_m2
            and a.metrics == b.metrics)


@pytest.mark.parametrize("program", ["short_xz.ngc", "circle_r50_f3000.ngc"])
def test_memo_over_shrinking_limits_gives_the_fresh_gains(program):
    sp = plan_toolpath(load_toolpath(DATA / program), UCP, feed_m_s=None, tol_m=2e-5)
    memo = EqualGainMemo()
    found = []
    for reserve in (1.0, 0.95, 0.88, 0.8, 0.7, 0.55, 0.3):
        design = design_machine(UCP, reserve, (1.0, 3.0))
        fresh = best_fixed_gains(sp, design)
        kept = best_fixed_gains(sp, design, memo=memo)
        assert _same(fresh, kept), reserve
        found.append(None if fresh is None else (fresh.kp["x"], fresh.kf["x"]))
        # the memo knew something: complete configurations are not simulated again
        assert np.any(memo.status == 3) or fresh is None
    assert len(set(found)) >= 3  # the limits did move the best gains
    assert found[-1] is None or found[-1] != found[0]


def test_memo_restarts_when_the_limits_grow_or_the_toolpath_changes():
    sp = plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), UCP, feed_m_s=None, tol_m=2e-5)
    other = plan_toolpath(load_toolpath(DATA / "circle_r50_f3000.ngc"), UCP, feed_m_s=None,
                          tol_m=2e-5)
    memo = EqualGainMemo()
    for setpoints, reserve in ((sp, 0.7), (sp, 1.0), (other, 0.9), (sp, 0.8)):
        design = design_machine(UCP, reserve, (1.0, 3.0))
        assert _same(best_fixed_gains(setpoints, design),
                     best_fixed_gains(setpoints, design, memo=memo)), (setpoints.source, reserve)


@pytest.mark.parametrize("program", ["short_xz.ngc", "circle_r50_f3000.ngc"])
def test_resumed_configurations_are_those_simulated_from_the_start(program):
    # the fast path (an abandoned configuration resumes from the chunk it was abandoned in)
    # against the slow one (its resume points cleared: simulated again from the first
    # sample): the same gains and the same memo, bit for bit
    sp = plan_toolpath(load_toolpath(DATA / program), UCP, feed_m_s=None, tol_m=2e-5)
    fast, slow = EqualGainMemo(), EqualGainMemo()
    resumed = 0
    for reserve in (1.0, 0.95, 0.88, 0.8, 0.7, 0.55, 0.3):
        design = design_machine(UCP, reserve, (1.0, 3.0))
        if slow.resume is not None:
            slow.resume[0][:] = -1
        waiting = (None if fast.resume is None
                   else (fast.resume[0] >= 0, fast.lower.copy(), fast.status.copy()))
        assert _same(best_fixed_gains(sp, design, memo=fast),
                     best_fixed_gains(sp, design, memo=slow)), reserve
        if waiting is not None:  # visited again: simulated on, or its peaks broke a limit
            mask, lower, status = waiting
            resumed += int(np.sum(mask & ((fast.lower != lower) | (fast.status != status))))
        for name in ("status", "sse", "lower"):
            np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name))
        known = fast.status != 1  # an infeasible one's peaks stop at different chunks
        np.testing.assert_array_equal(fast.peaks[known], slow.peaks[known])
    assert resumed > 0  # the fast path was taken
