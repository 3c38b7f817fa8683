"""The fast replay paths give the very bits of the plain ones (and of oga 7adc0aa).

- :func:`oga.model.simulate.run_axes` (the axes side by side) against :func:`oga.model.simulate.run`
  axis by axis, on perturbed plants of the uncertainty set;
- :func:`oga.model.contour.contour_error_of` with its kept path index against
  :func:`oga.model.contour.ce_series`;
- :func:`oga.model.metrics.contour_metrics`'s compiled pass against numpy's reductions (the
  code it replaced, kept below);
- whole :func:`oga.verify.verify` replays against those of oga at commit 7adc0aa (before these
  paths), on the nominal plant and perturbed ones: pinned first as SHA-256 digests, kept as
  arrays since (``tests/data/reference/verify.npz``, :mod:`references`; digests of floats pin
  one CPU), compared within tolerances measured across CPU configurations.
"""

from pathlib import Path

import numpy as np
import pytest
from numba import njit

from feedplan.read import load_toolpath
from feedplan.setpoints import AXES, Setpoints
from oga.model.contour import ce_series, contour_error_of, plane_axes
from oga.defaults import CE_WINDOW_SAMPLES
from oga.errors import InputError, OptionError
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, load_machine, machine_from_dict
from oga.model.metrics import contour_metrics
from oga.pipeline import plan_toolpath
from oga.search.robust.plants import scenario_set
from oga.model.simulate import axis_params, rest_state, run
from oga.model.response import simulate
import references

DATA = Path(__file__).parent / "data"
UCP = load_machine("ucp710")
SCEN = scenario_set(UCP, n=64, seed=17)
SP = plan_toolpath(load_toolpath(DATA / "reference_xz.ngc"), UCP, feed_m_s=None, tol_m=2e-5)


def _gains(n, seed=1):
    """Per-sample gains that wander inside the bounds (random walks, seeded)."""
    rng = np.random.default_rng(seed)
    kp = np.clip(3 + np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0), 1, 5)
    kf = np.clip(0.8 + np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0), 0, 1)
    return kp, kf


def _bits(a):
    return np.ascontiguousarray(a).view(np.int64)


def _three_axis_setpoints():
    """A 3-axis path: moves of every axis, slow crawls across the friction's cut, reversals
    and standstills (where the sub-steps and the skipped periods are taken)."""
    te = UCP.te
    t = np.arange(4000) * te
    pos = np.stack([0.02 * np.sin(2 * np.pi * 0.7 * t),
                    np.where(t < 2.0, 0.004 * t * t, 0.016 - 0.003 * (t - 2.0)),
                    np.where((t > 1.0) & (t < 1.5), 1e-3 * np.sin(np.pi * (t - 1.0) / 0.5) ** 2,
                             0.0)], axis=1)
    vel = np.gradient(pos, te, axis=0)
    vel[np.all(np.diff(pos, axis=0, prepend=pos[:1]) == 0, axis=1)] = 0.0
    zeros = np.zeros_like(pos)
    return Setpoints(dt=te, s=t, pos=pos, vel=vel, acc=zeros, jerk=zeros,
                     block=np.zeros(len(t), np.int64), rapid=np.zeros(len(t), bool), plane=None)


def _retimed(substeps, dead):
    """ucp710 (nominal) with other inner sub-steps and dead time."""
    data = UCP.model_dump(exclude_none=True)
    data["timing"].update(substeps=substeps, dead_time_samples=dead)
    return machine_from_dict(data)


PLANTS = [UCP, _retimed(3, 0), _retimed(1, 1)] + [SCEN.plants[i] for i in (0, 3, 40, 64, 70, 95)]


@pytest.mark.parametrize("sp", [SP, _three_axis_setpoints()], ids=["reference_xz", "3-axis"])
@pytest.mark.parametrize("plant", PLANTS, ids=lambda m: f"{m.name[-24:]}-{m.timing.substeps}-"
                                                         f"{m.timing.dead_time_samples}")
def test_simulate_is_run_axis_by_axis_bit_for_bit(sp, plant):
    kp, kf = _gains(len(sp))
    sim = simulate(sp, plant, kp, kf)
    moved = 0
    for c, a in enumerate(AXES):
        params = axis_params(plant, a)
        state = rest_state(params, sp.pos[0, c])
        p, u = np.empty(len(sp)), np.empty(len(sp))
        run(state, params, np.ascontiguousarray(sp.pos[:, c]), np.ascontiguousarray(sp.vel[:, c]),
            kp[:, c] * KP_SI_PER_M_MIN_PER_MM, np.ascontiguousarray(kf[:, c]), p, u)
        np.testing.assert_array_equal(_bits(sim.pos[:, c]), _bits(p))
        np.testing.assert_array_equal(_bits(sim.u[:, c]), _bits(u))
        moved += bool(np.any(u))
    assert moved == len(sp.moving_axes)


def test_run_axes_leaves_the_states_run_leaves():
    """The end states (the dead-time lines included), cut into pieces and resumed."""
    from oga.model.simulate import run_axes

    sp = _three_axis_setpoints()
    kp, kf = _gains(len(sp), seed=4)
    kp_si = kp * KP_SI_PER_M_MIN_PER_MM
    plant = SCEN.plants[70]  # a corner with an extra sample of dead time
    params = np.stack([axis_params(plant, a) for a in AXES])
    states = np.stack([rest_state(params[c], sp.pos[0, c]) for c in range(3)])
    ref = states.copy()
    pos, u = np.empty((len(sp), 3)), np.empty((len(sp), 3))
    for k0, k1 in ((0, 1), (1, 1700), (1700, len(sp))):  # a piece shorter than the dead time
        run_axes(states, params, np.arange(3), sp.pos[k0:k1], sp.vel[k0:k1], kp_si[k0:k1],
                 kf[k0:k1], pos[k0:k1], u[k0:k1])
    for c in range(3):
        p, uc = np.empty(len(sp)), np.empty(len(sp))
        run(ref[c], params[c], np.ascontiguousarray(sp.pos[:, c]),
            np.ascontiguousarray(sp.vel[:, c]), np.ascontiguousarray(kp_si[:, c]),
            np.ascontiguousarray(kf[:, c]), p, uc)
        np.testing.assert_array_equal(_bits(pos[:, c]), _bits(p))
        np.testing.assert_array_equal(_bits(u[:, c]), _bits(uc))
    np.testing.assert_array_equal(_bits(states), _bits(ref))


def test_contour_error_of_keeps_the_index_and_the_bits():
    sim = simulate(SP, UCP, 3.0, 0.8)
    other = simulate(SP, SCEN.plants[64], 2.0, 0.5)
    e1, e2, signed = plane_axes(SP.plane)
    for pa in (sim.pos, other.pos, sim.pos):  # the second and third calls use the kept index
        np.testing.assert_array_equal(
            _bits(contour_error_of(SP, pa)),
            _bits(ce_series(np.ascontiguousarray(SP.pos), pa, CE_WINDOW_SAMPLES, e1, e2, signed)))
    np.testing.assert_array_equal(
        _bits(contour_error_of(SP, sim.pos, window=7)),
        _bits(ce_series(np.ascontiguousarray(SP.pos), sim.pos, 7, e1, e2, signed)))
    bad = sim.pos.copy()
    bad[5, 1] = np.nan
    with pytest.raises(InputError, match="finite"):
        contour_error_of(SP, bad)
    with pytest.raises(InputError, match="shape"):
        contour_error_of(SP, sim.pos[:-1])
    with pytest.raises(OptionError, match="window"):
        contour_error_of(SP, sim.pos, window=0)


def _numpy_metrics(ce, pd, pa, keep):
    """contour_metrics' figures as oga 7adc0aa computed them (numpy reductions)."""
    a = np.abs(ce[keep])
    err_all = np.abs(pd - pa)
    err = err_all[keep]
    mse = float(np.mean(a * a))
    return (a.size, mse, float(np.sqrt(mse)), float(a.max()),
            *(float(v) for v in np.percentile(a, [50, 95, 99])),
            tuple(float(v) for v in err_all.max(axis=0)),
            tuple(float(v) for v in np.sqrt(np.mean(err * err, axis=0))))


@pytest.mark.parametrize("n", [1, 2, 7, 8, 9, 15, 16, 17, 127, 128, 129, 130, 255, 256, 257,
                               1000, 8191, 8193, 20011])
def test_contour_metrics_are_numpys_to_the_bit(n):
    rng = np.random.default_rng(n)
    scale = np.exp(rng.uniform(-30, 0, n))  # a wide range: the order of the sums shows
    ce = rng.standard_normal(n) * scale
    pd = rng.standard_normal((n, 3))
    pa = pd + rng.standard_normal((n, 3)) * scale[:, None]
    for keep in (np.ones(n, bool), rng.random(n) < 0.7):
        keep[0] = True
        m = contour_metrics(ce, pd, pa, keep)
        got = (m.n, m.mse_m2, m.rms_m, m.max_abs_m, m.p50_m, m.p95_m, m.p99_m,
               m.track_max_m, m.track_rms_m)
        want = _numpy_metrics(ce, pd, pa, keep)
        assert repr(got) == repr(want)  # repr: every float to the last bit, NaN equal to NaN
    if n > 3:  # NaN propagates as numpy's maximum does
        ce[n // 2] = np.nan
        pa[n // 3, 1] = np.nan
        keep = np.ones(n, bool)
        m = contour_metrics(ce, pd, pa, keep)
        want = _numpy_metrics(ce, pd, pa, keep)
        assert repr((m.mse_m2, m.max_abs_m, m.track_max_m, m.track_rms_m)) == repr(
            (want[1], want[3], want[7], want[8]))


@pytest.mark.portable
@pytest.mark.parametrize("i", references.VERIFY_PLANTS)
def test_verify_is_that_of_7adc0aa(i):
    """Plant i of scenario_set(ucp710, 64, seed 17) (0: nominal; the exact kernel, as at
    7adc0aa: the plants now set the linear friction map at rest, tests/test_friction_linear.py
    bounds its departure), reference_xz as planned at 7adc0aa, gains that wander."""
    got = references.cases("verify")[f"plant {i}"]()
    assert references.compare("verify", f"plant {i}", got) == []


def test_largest_gain_steps_are_numpys():
    from oga.verify.replay import _largest_steps

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 50):
        x = rng.standard_normal((n, 3)) * np.exp(rng.uniform(-30, 3, (n, 3)))
        want = np.abs(np.diff(x, axis=0)).max(axis=0, initial=0.0)
        np.testing.assert_array_equal(_bits(_largest_steps(x)), _bits(want))
        if n > 2:
            x[1, 2] = np.nan  # NaN is kept, as numpy's maximum keeps it
            want = np.abs(np.diff(x, axis=0)).max(axis=0, initial=0.0)
            assert repr(_largest_steps(x).tolist()) == repr(want.tolist())


def _friction_machines():
    """ucp710, perturbed plants, and the friction's special cases (no Stribeck peak, no
    Coulomb friction, none at all)."""
    out = [UCP, SCEN.plants[0], SCEN.plants[64], SCEN.plants[95]]
    for change in ({"static_n": 60.0}, {"coulomb_n": 0.0}, {"coulomb_n": 0.0, "static_n": 0.0}):
        data = UCP.model_dump(exclude_none=True)
        data["axes"]["x"]["cascade"].update(change)
        out.append(machine_from_dict(data))
    return out


_R2 = 26  # oga.model.simulate._R2_CUT


@pytest.mark.parametrize("machine", _friction_machines(), ids=lambda m: str(m.digest()[:8]))
def test_branchless_friction_is_friction_nonlinear_bit_for_bit(machine):
    """The sub-steps' friction against friction_nonlinear (unchanged since 7adc0aa: its
    exponentials only where needed)."""
    from oga.model.simulate import _friction_flat, friction_nonlinear

    @njit
    def both(params, vs, out):
        for k in range(vs.size):
            out[0, k] = _friction_flat(params, vs[k])
            out[1, k] = friction_nonlinear(params, vs[k])

    params = axis_params(machine, "x")
    rng = np.random.default_rng(3)
    cas = machine.axes["x"].cascade
    cuts = np.array([cas.friction_smoothing_m_s * 20.0, cas.stribeck_m_s * np.sqrt(params[_R2]),
                     cas.stribeck_m_s * np.sqrt(746.0), 1e-4, 1e-3])
    near = (cuts[:, None] * (1.0 + np.arange(-40, 41)[None, :] * 2.0 ** -52)).ravel()
    vs = np.concatenate([
        rng.standard_normal(100_000) * 10.0 ** rng.uniform(-30, 1, 100_000),
        near, -near, [0.0, -0.0, 5e-324, -5e-324, np.inf, -np.inf, np.nan, -np.nan, 1e300],
    ])
    out = np.empty((2, vs.size))
    both(params, vs, out)
    np.testing.assert_array_equal(_bits(out[0]), _bits(out[1]))


def test_command_peaks_are_the_largest_quotients_bit_for_bit():
    """command_peaks divides the largest differences once: the largest of numpy's quotients
    (a NaN command passed over, as ``max`` passes over it)."""
    from oga.model.kinematics import command_peaks

    rng = np.random.default_rng(11)
    for n, te in ((1, 1e-3), (7, 1e-3), (5000, 1e-3), (5000, 7.3e-4), (300, 0.25)):
        u = rng.standard_normal(n) * 10.0 ** rng.uniform(-12, 1, n)
        for check in (np.ones(n, bool), rng.random(n) < 0.5):
            if n > 10:
                u[n // 2] = np.nan
            full = np.concatenate([[0.0, 0.0], u])
            d1 = np.abs(np.diff(full))[1:]
            d2 = np.abs(full[2:] - 2.0 * full[1:-1] + full[:-2])
            want = [np.fmax.reduce(x[check], initial=0.0) for x in
                    (np.abs(u), d1 / te, d2 / (te * te))]
            np.testing.assert_array_equal(_bits(np.array(command_peaks(u, check, te))),
                                          _bits(np.array(want)))


def test_eq2_excess_is_the_largest_excess_bit_for_bit():
    """eq2_excess scales the largest differences once: the largest of numpy's per-sample
    excesses (a NaN command passed over)."""
    from oga.model.kinematics import eq2_excess

    rng = np.random.default_rng(12)
    te = 1e-3
    for n in (1, 3, 40, 400):
        for lim in ((0.5, 2.5, 10.0), (0.05, 0.3, 1.7), (1e-9, 1e-9, 1e-9)):
            u = rng.standard_normal(n + 5) * 10.0 ** rng.uniform(-9, 0, n + 5)
            if n > 10:
                u[n // 3] = np.nan
            u1, u2 = rng.standard_normal(2) * 1e-3
            check = rng.random(n + 5) < 0.8
            full = np.concatenate([[u2, u1], u[:n]])
            d1 = np.abs(np.diff(full))[1:]
            d2 = np.abs(full[2:] - 2.0 * full[1:-1] + full[:-2])
            terms = [np.abs(u[:n]) / lim[0] - 1.0, d1 / (lim[1] * te) - 1.0,
                     d2 / (lim[2] * te * te) - 1.0]
            want = np.fmax.reduce(np.concatenate([t[check[:n]] for t in terms]), initial=0.0)
            got = eq2_excess(u, u1, u2, *lim, te, n, check)
            assert np.float64(got).view(np.int64) == np.float64(want).view(np.int64)
