"""The robust search's fixed costs, cut, give the bits of the paths they replace.

- the stable Kp range: the loop's response from the shared table of ``z`` and ``z^-d``
  against :func:`oga.model.stability._h_modal_grid`, its gain margin (compiled phase crossovers)
  against the Python path (scipy's ``brentq`` on ``Im H``), and the ends of the compiled walk
  (blocks without a sign change skipped, the closed loop's eigenvalues by the real ``geev``
  away from the unit circle) against the Python walk over :func:`oga.model.stability._margins`, on
  the 96 plants of ucp710's default set, and that stability decision against the complex
  ``geev``'s;
- the sub-step matrices, memoised and shared by the packed parameters and the stability
  loops, against a fresh ``scipy.linalg.expm`` and the sequence composed here, on the same
  plants and the presets; the packed parameters whichever asks first;
- the replay's checks: the percentiles of :func:`oga.model.metrics.contour_metrics` against
  ``np.percentile``, the rest test of :func:`oga.model.response.simulate` against numpy's, the
  machine's memoised digest and limits against fresh ones.
"""

import gc
import importlib
import math
from collections import OrderedDict

import numpy as np
import pytest
from numba import njit
from scipy.linalg import expm
from scipy.optimize import brentq

import oga.model.linear as linear
import oga.model.machine as machine_mod
import oga.model.stability as stability
from oga.model.machine import KP_SI_PER_M_MIN_PER_MM, PRESETS, load_machine
from oga.model.metrics import _QUANTILES, _percentiles
from oga.search.robust.plants import scenario_set

sim = importlib.import_module("oga.model.simulate")  # the module, not oga's function
response = importlib.import_module("oga.model.response")

UCP = load_machine("ucp710")
PLANTS = scenario_set(UCP).plants  # the default set: 64 Monte Carlo plants, 32 corners
MACHINES = tuple(load_machine(p) for p in PRESETS) + PLANTS


@pytest.fixture(autouse=True)
def fresh_memo(monkeypatch):
    for name in ("_LOOPS", "_TABLES", "_ENDS"):
        monkeypatch.setattr(stability, name, OrderedDict())


def _bits(x):
    return np.asarray(x, dtype=np.float64).tobytes() if np.isrealobj(x) else np.asarray(x).tobytes()


def _python_gain_margin(loop):
    """The gain margin as :class:`oga.model.stability._Loop` computed it in Python."""
    w, h = loop.w, loop.h
    turns = np.floor((loop.phase + math.pi) / (2.0 * math.pi))
    crossings = [
        stability._root(lambda x: loop.response(x).imag, w[i], w[i + 1], h[i].imag, h[i + 1].imag)
        for i in np.flatnonzero(turns[:-1] != turns[1:])
    ]
    if h[-1].real < 0.0:
        crossings.append(w[-1])
    gm, wc_best = math.inf, math.nan
    for wc in crossings:
        gm_i = -20.0 * math.log10(abs(loop.response(wc)))
        if gm_i < gm:
            gm, wc_best = gm_i, float(wc)
    return gm, wc_best


def test_loop_response_and_gain_margin_are_the_python_paths_on_the_set():
    assert len(PLANTS) == 96
    crossed = 0
    for plant in PLANTS:
        for axis in ("x", "z"):
            loop = stability._Loop(plant, axis)
            lam, res, dead = loop.modal
            grid = stability._h_modal_grid(lam, res, dead, loop.te, loop.w)
            assert _bits(loop.h) == _bits(grid)
            gm, wc = _python_gain_margin(loop)
            assert _bits(loop.gm_db) == _bits(gm)
            assert _bits(loop.w_phase_crossover_rad_s) == _bits(wc)
            crossed += math.isfinite(gm)
    assert crossed == 2 * len(PLANTS)  # every loop has phase crossovers to refine


def test_stable_ends_are_the_python_walk_on_the_set():
    ends = set()
    for plant in PLANTS:
        for axis in ("x", "z"):
            got = stability.stable_ends(plant, axis)
            want = stability._walk(stability._loop(plant, axis), plant.gains)
            assert _bits(got) == _bits(want), (plant.name, axis, got, want)
            ends.add(got)
    assert len(ends) > 10


def test_closed_loop_stability_is_the_complex_eigenvalues_decision():
    """The real ``geev`` with its guard decides as the complex ``geev`` (the walk's reference)
    on the loops of the set over Kp from 0.05 to 20 (m/min)/mm, across the stability edge;
    nearer 1 than the guard, and on a matrix that is not finite, the complex one decides."""
    decided = set()
    for plant in PLANTS[::3]:
        for axis in ("x", "z"):
            loop = stability._Loop(plant, axis)
            n = loop.a.shape[0]
            work = (np.empty((n, n), dtype=complex), np.empty((n, n)), np.empty(n), np.empty(n))
            for kp in np.linspace(0.05, 20.0, 120) * KP_SI_PER_M_MIN_PER_MM:
                acl = loop.a - loop.b @ (kp * loop.c)
                want = bool(np.max(np.abs(_complex_eigvals(acl.astype(complex)))) < 1.0)
                assert stability._closed_loop_stable(loop.a, loop.b, loop.c, kp, *work) == want
                decided.add(want)
    assert decided == {True, False}
    work = (np.empty((2, 2), dtype=complex), np.empty((2, 2)), np.empty(2), np.empty(2))
    for rho in (1.0 - 1e-9, 1.0 + 1e-9, 1.0):
        a = np.diag([rho, 0.5])
        got = stability._closed_loop_stable(a, np.zeros((2, 1)), np.zeros((1, 2)), 1.0, *work)
        assert got == (rho < 1.0)
    with pytest.raises(np.linalg.LinAlgError):
        stability._closed_loop_stable(np.diag([np.nan, 0.5]), np.zeros((2, 1)),
                                      np.zeros((1, 2)), 1.0, *work)


@njit
def _complex_eigvals(a):
    return np.linalg.eigvals(a)


def _fresh_matrices(cas, h):
    m, tau = cas.mass_kg, cas.force_lag_s
    aug = np.zeros((5, 5))
    aug[:3, :3] = [[0.0, 1.0, 0.0], [0.0, -cas.viscous_n_s_m / m, 1.0 / m], [0.0, 0.0, -1.0 / tau]]
    aug[:3, 3:] = [[0.0, 0.0], [0.0, -1.0 / m], [1.0 / tau, 0.0]]
    e = expm(aug * h)
    ad, bd = e[:3, :3].copy(), e[:3, 3:].copy()
    ad[:, 0] = (1.0, 0.0, 0.0)
    ad[2, 1] = 0.0
    bd[2, 1] = 0.0
    return ad, bd


def test_memoised_substep_matrices_are_a_fresh_expm_and_not_shared():
    linear._matrices.cache_clear()
    linear._sequence.cache_clear()
    for machine in MACHINES:
        n_sub = machine.timing.substeps
        h = machine.timing.te_s / n_sub
        for axis, model in machine.axes.items():
            cas = model.cascade
            if cas is None:
                continue
            ad, bd = _fresh_matrices(cas, h)
            for _ in range(2):  # computed, then memoised
                got = linear.substep_matrices(cas, h)
                assert _bits(got[0]) == _bits(ad) and _bits(got[1]) == _bits(bd)
                a, b = linear.substep_sequence(machine, axis)
                m_sub = np.zeros((4, 4))
                bf = bd[:, 0] * cas.kv_n_s_m
                m_sub[:3, :3] = ad
                m_sub[:3, 1] -= bf
                m_sub[:3, 3] = bf / cas.tn_s
                m_sub[3, 1], m_sub[3, 3] = -h, 1.0
                n_in = np.zeros((4, 2))
                n_in[:3, 0], n_in[3, 0], n_in[:3, 1] = bf, h, bd[:, 1]
                want_a, want_b = [np.eye(4)], [np.zeros((4, 2))]
                for _ in range(n_sub):
                    want_a.append(m_sub @ want_a[-1])
                    want_b.append(m_sub @ want_b[-1] + n_in)
                assert _bits(a) == _bits(np.array(want_a)) and _bits(b) == _bits(np.array(want_b))
                a[...] = 0.0  # the caller's copy: the memo is not touched
                got[0][...] = 0.0
    assert linear._matrices.cache_info().hits > 0


def test_packed_parameters_do_not_depend_on_who_asked_first():
    def packs():
        return [sim._pack(m, a, lifted) for m in MACHINES[::7] for a in m.axes
                for lifted in (True, False)]

    linear._matrices.cache_clear()
    linear._sequence.cache_clear()
    cold = packs()
    linear._matrices.cache_clear()
    linear._sequence.cache_clear()
    for m in MACHINES[::7]:
        for a in m.axes:
            stability._Loop(m, a)  # the loops compute the sub-step matrices first
    assert [_bits(p) for p in packs()] == [_bits(p) for p in cold]


def test_percentiles_are_numpys():
    rng = np.random.default_rng(11)
    cases = [np.array([1.0]), np.array([2.0, 1.0]), np.zeros(100), np.array([0.0, np.inf, 1.0]),
             np.full(3, np.inf), np.array([1.0, np.nan, 2.0])]
    for n in list(range(1, 40)) + [101, 1000, 2917, 20000]:
        cases.append(np.abs(rng.normal(size=n)) * 1e-6)
        cases.append(rng.integers(0, 3, size=n).astype(float))  # many ties
        x = np.abs(rng.normal(size=n))
        x[: n // 2] = 0.0
        cases.append(x)
        cases.append(np.sort(x))
    with np.errstate(invalid="ignore"):
        for c in cases:
            assert _bits(_percentiles(c, _QUANTILES)) == _bits(np.percentile(c, [50, 95, 99])), c


def test_rest_test_is_numpys():
    rng = np.random.default_rng(2)
    for _ in range(300):
        n = int(rng.integers(1, 6))
        pd = rng.choice([0.0, -0.0, 1.0, np.nan], n)
        vd = rng.choice([0.0, -0.0, 1e-300, np.nan], n)
        want = bool(np.all(pd == pd[0])) and not bool(np.any(vd))
        assert response._still(pd, vd) == want


def test_machine_memos_are_fresh_values_and_go_with_the_machine():
    m = load_machine("ucp710")
    d, lim = m.digest(), m.axis_limits()
    assert m.digest() is d and m.axis_limits() is lim  # memoised
    assert d == machine_mod.json_digest(m.model_dump(mode="json", exclude_none=True))
    fresh = m._axis_limits()
    for name in ("vmax_m_s", "amax_m_s2", "jmax_m_s3"):
        assert _bits(getattr(lim, name)) == _bits(getattr(fresh, name))
        assert not getattr(lim, name).flags.writeable
    other = m.model_copy(update={"name": "copy"})  # copies the instance's __dict__
    assert other.digest() != d
    keys = {id(m), id(other)}
    assert keys <= set(machine_mod._MACHINE_MEMOS)
    del m, other
    gc.collect()
    assert not keys & set(machine_mod._MACHINE_MEMOS)


def test_verify_limit_matrix_is_the_stacked_axis_limits():
    from oga.model.plant import plant_of

    for machine in MACHINES[:: 5]:
        lim = machine.axis_limits()
        want = np.stack([lim.vmax_m_s, lim.amax_m_s2, lim.jmax_m_s3], axis=1)
        got = plant_of(machine).limits
        assert _bits(got) == _bits(want) and not got.flags.writeable
