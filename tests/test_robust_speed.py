"""The robust search's faster paths give the numbers of the slower ones they replace.

- the stable Kp range: the loop's response in modal form (``oga.model.stability._modal``) against
  the batched solve of ``C (zI - A)^-1 B``, and the ends walked lazily
  (:func:`oga.model.stability.stable_ends`) against the whole margin table of the previous
  :func:`oga.model.stability.stable_range` (solve path, fresh memo), over the plants of ucp710's
  default uncertainty set; the loop's shared frequency grid and compiled phase unwrap
  against numpy's, bit for bit;
- :func:`oga.model.response.simulate` skipping an axis whose setpoint never moves, against the
  kernel's own replay of that axis, bit for bit;
- the largest following error per axis in one compiled pass (:func:`oga.model.metrics.track_max`)
  against numpy's.
"""

from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest

import oga.model.stability as stability
from feedplan.read import load_toolpath
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.model.metrics import track_max
from oga.pipeline import plan_toolpath
from oga.search.robust.plants import scenario_set
from oga.model.simulate import axis_params, simulate_axis
from oga.model.response import simulate

DATA = Path(__file__).parent / "data"
ROBUST = load_machine("ucp710")
#: 16 Monte Carlo plants and the 32 corners (the extremes of the set)
PLANTS = scenario_set(ROBUST, n=16, seed=5).plants


@pytest.fixture
def fresh_memo(monkeypatch):
    """Empty memos of loops, margin tables and ends (restored afterwards)."""
    for name in ("_LOOPS", "_TABLES", "_ENDS"):
        monkeypatch.setattr(stability, name, OrderedDict())


def test_modal_response_equals_the_solve_on_every_plant():
    for plant in PLANTS[::3]:
        for axis in ("x", "z"):
            loop = stability._Loop(plant, axis)
            assert loop.modal is not None  # balanced, the set's loops are far from defective
            exact = stability._response(loop.a, loop.b, loop.c, loop.w, loop.te)
            assert np.max(np.abs(loop.h / exact - 1.0)) < 1e-9
            for w in loop.w[::397]:
                assert abs(loop.response(float(w)) / stability._response(
                    loop.a, loop.b, loop.c, np.array([w]), loop.te)[0] - 1.0) < 1e-9


def test_modal_form_refused_when_defective():
    # a Jordan block: eigenvectors (numerically) parallel, so the exact solve is kept
    a = np.array([[0.5, 1.0, 0.0], [0.0, 0.5, 1.0], [0.0, 0.0, 0.5]])
    assert stability._modal(a, np.ones((3, 1)), np.ones((1, 3)), 0) is None


def test_stable_ends_equal_the_previous_stable_range(fresh_memo, monkeypatch):
    fast = [stability.stable_ends(p, a) for p in PLANTS for a in ("x", "z")]
    fast_pm = {(i, a): stability._margins(stability._loop(p, a), 2.0).pm_deg
               for i, p in enumerate(PLANTS[:6]) for a in ("x", "z")}
    # the previous implementation: the whole table, every response by the batched solve
    monkeypatch.setattr(stability, "_modal", lambda *args: None)
    monkeypatch.setattr(stability, "_LOOPS", OrderedDict())
    monkeypatch.setattr(stability, "_TABLES", OrderedDict())
    slow = []
    for p in PLANTS:
        for a in ("x", "z"):
            r = stability.stable_range(p, a)
            slow.append((r.kp_min, r.kp_max))
    assert fast == slow
    assert len(set(slow)) > 3  # the set's plants do have different ranges
    for (i, a), pm in fast_pm.items():
        ref = stability._margins(stability._loop(PLANTS[i], a), 2.0).pm_deg
        assert pm == pytest.approx(ref, abs=1e-8)


def test_stable_ends_reads_a_memoised_table_and_reports_an_empty_range(fresh_memo):
    r = stability.stable_range(ROBUST, "x")
    assert stability.stable_ends(ROBUST, "x") == (r.kp_min, r.kp_max)
    data = ROBUST.model_dump(mode="json", exclude_none=True)
    data["gains"]["pm_min_deg"] = 89.9  # no Kp of the grid has that much phase margin
    strict = machine_from_dict(data)
    assert all(np.isnan(stability.stable_ends(strict, "x")))  # walked: no table memoised
    assert stability.stable_range(strict, "x").status == "empty"


@pytest.mark.parametrize("program, still", [("reference_xz.ngc", 1), ("circle_r50_f3000.ngc", 2)])
def test_still_axis_skipped_gives_the_kernels_bits(program, still):
    sp = plan_toolpath(load_toolpath(DATA / program), ROBUST, feed_m_s=None, tol_m=2e-5)
    assert still not in sp.moving_axes
    n = len(sp)
    rng = np.random.default_rng(3)
    kp = rng.uniform(1.0, 3.0, (n, 3))  # gains that vary: nothing to do with rest
    kf = rng.uniform(0.3, 1.0, (n, 3))
    for plant in PLANTS[::8] + (ROBUST,):
        sim = simulate(sp, plant, kp, kf)
        axis = "xyz"[still]
        pd = np.ascontiguousarray(sp.pos[:, still])
        p, u = simulate_axis(axis_params(plant, axis), pd[0], pd, sp.vel[:, still],
                             kp[:, still] * KP_SI_PER_M_MIN_PER_MM, kf[:, still])
        assert np.array_equal(sim.pos[:, still], p)
        assert np.array_equal(sim.u[:, still], u)
        assert not np.any(u)
        moving = sp.moving_axes[0]  # the moving axes are replayed, not at rest
        assert np.any(sim.u[:, moving])


def test_loop_grid_and_unwrapped_phase_are_numpys():
    """The shared frequency grid and the compiled unwrap (:class:`oga.model.stability._Loop`) against
    numpy's geomspace and unwrap, bit for bit: on the loops of the set's plants, and on
    phases with jumps of every size, exactly +-pi among them."""
    for plant in PLANTS[::5]:
        loop = stability._Loop(plant, "x")
        w = np.geomspace(stability._W_LOW_TE / loop.te, np.pi / loop.te, stability._GRID_POINTS)
        np.testing.assert_array_equal(loop.w.view(np.int64), w.view(np.int64))
        ref = np.unwrap(np.angle(loop.h))
        assert np.ptp(ref) > 2 * np.pi  # the phase does wrap
        np.testing.assert_array_equal(loop.phase.view(np.int64), ref.view(np.int64))
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 1000):
        p = np.cumsum(rng.uniform(-9.0, 9.0, n))
        p[rng.random(n) < 0.2] = 0.0
        if n > 3:
            p[:4] = 0.0, np.pi, 0.0, -np.pi  # differences of exactly +pi and -pi
        np.testing.assert_array_equal(stability._unwrap(p).view(np.int64),
                                      np.unwrap(p).view(np.int64))


def test_track_max_is_numpys_column_max_of_the_abs_error():
    """The compiled largest following error (:func:`oga.model.metrics.track_max`) against numpy's,
    bit for bit, NaN included, on replays of the set's plants and on a column with a NaN."""
    sp = plan_toolpath(load_toolpath(DATA / "short_xz.ngc"), ROBUST, feed_m_s=None, tol_m=2e-5)
    n = len(sp)
    for plant, kp in zip(PLANTS[::9], (1.2, 2.1, 3.0, 2.6, 1.7, 2.9)):
        sim = simulate(sp, plant, np.full((n, 3), kp), np.full((n, 3), 0.8))
        ref = np.abs(sp.pos - sim.pos).max(axis=0)
        assert ref[0] > 0 and ref[2] > 0
        np.testing.assert_array_equal(track_max(sp.pos, sim.pos).view(np.int64),
                                      ref.view(np.int64))
    pa = np.array(sim.pos)
    pa[n // 2, 2] = np.nan
    got = track_max(sp.pos, pa)
    ref = np.abs(sp.pos - pa).max(axis=0)
    assert np.isnan(got[2]) and np.isnan(ref[2])
    np.testing.assert_array_equal(got[:2].view(np.int64), ref[:2].view(np.int64))
