"""An exported gain table replayed by an independent reference simulator.

The issue's acceptance asks that "the schedules replayed independently give the
same ratios". Here the product runs as a user runs it (``oga optimize`` through
:func:`oga.cli.main`, default full mode, best fixed baseline, machine ucp710) on
``tests/data/short_xz.ngc``, and only its output FILES are read back: the gain
table CSV and the summary JSON (and the setpoints CSV of ``oga plan``).

What is independent of what:

- the machine numbers come from ``oga/presets/ucp710.toml`` parsed with
  :mod:`tomllib`, not from ``oga.model.machine``;
- the simulator (:func:`replay_axis`) is written in plain Python/numpy/scipy from
  the model's description (the comments of ``oga/presets/ucp710.toml`` and the module
  docstring of ``oga/model/simulate.py``): its sub-step matrices come from
  :func:`scipy.linalg.expm` of the continuous equations, one sub-step after the
  other everywhere (no lifted step over Te, no compiled code);
- the contour error (:func:`contour_error`) is the brute-force least distance to
  every segment of the setpoint polyline within +-400 samples;
- eq. 2 is checked with plain numpy differences and the TOML's limits.

The only things taken from oga are the files it wrote. The reference replays
the table's gains and the summary's baseline fixed gains and must reproduce the
summary's ``ratio_mse`` and its contour-error figures to rounding; a corrupted
table must move the ratio by far more than that tolerance.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import re
import tomllib
from collections import deque
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from oga.cli import main

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
PROGRAM = DATA / "short_xz.ngc"
PRESET = ROOT / "oga" / "presets" / "ucp710.toml"
AXES = ("x", "y", "z")
#: (m/min)/mm -> 1/s.
KP_SI = 1000.0 / 60.0
#: Default friction smoothing velocity (``s = tanh(v / 1e-4 m/s)``), used when
#: the machine file does not set ``friction_smoothing_m_s``.
EPS_DEFAULT_M_S = 1e-4
#: Segments each side of a sample searched by the brute-force contour error.
CE_WINDOW = 400
#: Relative agreement demanded between this reference and the summary. The two
#: simulators implement the same discrete model and differ by floating-point
#: rounding only (oga takes an exact lifted step over Te where the friction is
#: constant, this one always sub-steps; the matrix exponentials are computed
#: differently). Positions of ~0.03 m agree to ~1e-16 m, which is ~1e-11 of a
#: contour error of a few um; measured on short_xz: ratio_mse 3.9e-12, MSE and RMS
#: figures <= 3.4e-12, max and p95 CE <= 1e-12, eq. 2 ratios <= 4.2e-13 relative.
#: 1e-9 leaves a margin of over two orders of magnitude for other BLAS/platforms
#: and is still far below any real change of the schedule (X's Kp 0.1 % high over
#: 300 samples moves the ratio by 3e-4, see test_a_corrupted_table_is_caught).
RTOL = 1e-9


# --- the product, run as a user runs it ------------------------------------------------


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """Run ``oga optimize`` and ``oga plan`` on short_xz and read back their files.

    Returns
    -------
    dict
        ``table`` (column name -> ndarray), ``summary`` (the JSON as a dict),
        ``plan`` (column name -> ndarray, the setpoints CSV of ``oga plan``).
    """
    out = tmp_path_factory.mktemp("replay")
    table, summary, setpoints = out / "T.csv", out / "S.json", out / "P.csv"
    assert main(["optimize", str(PROGRAM), "--out", str(table), "--summary", str(summary),
                 "--nominal"]) == 0
    assert main(["plan", str(PROGRAM), "--out", str(setpoints)]) == 0
    return {
        "table": read_csv(table),
        "summary": json.loads(summary.read_text()),
        "plan": read_csv(setpoints),
    }


@pytest.fixture(scope="module")
def machine():
    """The preset ucp710 as parsed by :mod:`tomllib` (a plain dict)."""
    with PRESET.open("rb") as f:
        return tomllib.load(f)


@pytest.fixture(scope="module")
def replays(outputs, machine):
    """Reference replays of the table's gains and of the summary's baseline gains.

    Returns
    -------
    dict
        ``pd`` (N, 3) setpoints of the table; ``opt`` and ``base``: each a dict
        with ``pos`` (N, 3), ``u`` (N, 3), ``ce`` (N,) of the replay.
    """
    tab, summ = outputs["table"], outputs["summary"]
    pd_, vd = setpoint_arrays(tab)
    n = len(pd_)
    kp_opt = np.stack([tab[f"{a}_kp_m_min_per_mm"] for a in AXES], axis=1)
    kf_opt = np.stack([tab[f"{a}_kf"] for a in AXES], axis=1)
    kp_base = np.tile([summ["baseline"]["kp"][a] for a in AXES], (n, 1))
    kf_base = np.tile([summ["baseline"]["kf"][a] for a in AXES], (n, 1))
    return {
        "pd": pd_,
        "opt": replay(machine, pd_, vd, kp_opt, kf_opt),
        "base": replay(machine, pd_, vd, kp_base, kf_base),
    }


# --- helpers ------------------------------------------------------------------------------


def read_csv(path: Path) -> dict[str, np.ndarray]:
    """Read a CSV file with a header into float64 columns.

    Parameters
    ----------
    path : Path
        The file; every cell must be a number.

    Returns
    -------
    dict of str to ndarray, shape (N,)
        One entry per column, in file order (``float`` of the text: exact for the
        17 significant digits oga writes).
    """
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    return {name: np.array([float(r[i]) for r in body]) for i, name in enumerate(header)}


def setpoint_arrays(tab: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Setpoint positions and velocities of a table as (N, 3) arrays (x, y, z).

    Parameters
    ----------
    tab : dict of str to ndarray
        Columns of the gain table (or of the setpoints CSV).

    Returns
    -------
    pos, vel : ndarray, shape (N, 3)
        m and m/s.
    """
    pos = np.stack([tab[f"{a}_pos_m"] for a in AXES], axis=1)
    vel = np.stack([tab[f"{a}_vel_m_s"] for a in AXES], axis=1)
    return pos, vel


def substep_matrices(cascade: dict, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of one axis's linear mechanics over ``h``.

    The continuous model, state ``[p, v, F]`` and held inputs ``[F_cmd, F_n]``::

        dp/dt = v
        m dv/dt = F - B v - F_n
        tau dF/dt = F_cmd - F

    discretised with the augmented exponential ``expm([[A, Bc], [0, 0]] h)``.

    Parameters
    ----------
    cascade : dict
        The axis's ``cascade`` table of the machine file.
    h : float
        Sub-step, s.

    Returns
    -------
    ad : ndarray, shape (3, 3)
    bd : ndarray, shape (3, 2)
    """
    m, b, tau = cascade["mass_kg"], cascade["viscous_n_s_m"], cascade["force_lag_s"]
    aug = np.zeros((5, 5))
    aug[0, 1] = 1.0
    aug[1, 1], aug[1, 2], aug[1, 4] = -b / m, 1.0 / m, -1.0 / m
    aug[2, 2], aug[2, 3] = -1.0 / tau, 1.0 / tau
    e = expm(aug * h)
    return e[:3, :3], e[:3, 3:]


def replay_axis(cascade, timing, pd, vd, kp_m_min_per_mm, kf):
    """Replay one cascade axis from rest at its first setpoint.

    Per sample k: measure ``p_k``; ``u_k = Kp_k (pd_k - p_k) + Kf_k vd_k`` (Kp in
    1/s); the velocity loop receives ``u_{k-d}`` (0 before the start) during the
    sample; ``substeps`` sub-steps of ``h = Te / substeps``, each: the PI
    ``F_cmd = Kv (e + I / Tn)`` limited to the force limit with ``e = u - v``,
    the integral ``I += h e`` frozen while the command is limited unless ``e``
    drives it back out, ``F_n = (Fc + (Fs - Fc) exp(-(v/vs)^2)) tanh(v/eps)`` at
    the sub-step start, then ``[p, v, F]`` propagated by the exact sub-step
    matrices with ``F_cmd`` and ``F_n`` held.

    Parameters
    ----------
    cascade : dict
        The axis's ``cascade`` table of the machine file.
    timing : dict
        The machine file's ``timing`` table.
    pd, vd : ndarray, shape (N,)
        Setpoint position (m) and velocity (m/s).
    kp_m_min_per_mm, kf : ndarray, shape (N,)
        Gains per sample.

    Returns
    -------
    pos, u : ndarray, shape (N,)
        Measured positions ``p_k`` (m) and velocity commands ``u_k`` (m/s).
    """
    nsub = int(timing["substeps"])
    h = timing["te_s"] / nsub
    ad, bd = substep_matrices(cascade, h)
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = ad.tolist()
    (b00, b01), (b10, b11), (b20, b21) = bd.tolist()
    kv, tn, flim = cascade["kv_n_s_m"], cascade["tn_s"], cascade["force_limit_n"]
    fc, fs, vs = cascade["coulomb_n"], cascade["static_n"], cascade["stribeck_m_s"]
    eps = cascade.get("friction_smoothing_m_s", EPS_DEFAULT_M_S)
    line = deque([0.0] * int(timing["dead_time_samples"]))
    n = len(pd)
    pos, u = np.empty(n), np.empty(n)
    p, v, f, integ = float(pd[0]), 0.0, 0.0, 0.0
    for k in range(n):
        pos[k] = p
        uk = kp_m_min_per_mm[k] * KP_SI * (pd[k] - p) + kf[k] * vd[k]
        u[k] = uk
        line.append(uk)
        ua = line.popleft()
        for _ in range(nsub):
            e = ua - v
            raw = kv * (e + integ / tn)
            fcmd = min(max(raw, -flim), flim)
            if fcmd == raw or (raw > 0.0) != (e > 0.0):
                integ += h * e
            fn = (fc + (fs - fc) * math.exp(-((v / vs) ** 2))) * math.tanh(v / eps)
            p, v, f = (
                a00 * p + a01 * v + a02 * f + b00 * fcmd + b01 * fn,
                a10 * p + a11 * v + a12 * f + b10 * fcmd + b11 * fn,
                a20 * p + a21 * v + a22 * f + b20 * fcmd + b21 * fn,
            )
    return pos, u


def contour_error(pd: np.ndarray, pa: np.ndarray, window: int = CE_WINDOW) -> np.ndarray:
    """Unsigned contour error by brute force.

    Parameters
    ----------
    pd : ndarray, shape (N, 3)
        Setpoints: the vertices of the desired polyline, m.
    pa : ndarray, shape (N, 3)
        Actual positions, m.
    window : int, optional
        For sample k every segment ``pd[i] pd[i+1]`` with ``|i - k| <= window``.

    Returns
    -------
    ndarray, shape (N,)
        Least distance from ``pa[k]`` to those segments, m.
    """
    n = len(pd)
    a, d = pd[:-1], np.diff(pd, axis=0)
    l2 = np.einsum("ij,ij->i", d, d)
    out = np.empty(n)
    offsets = np.arange(-window, window + 1)
    for lo in range(0, n, 256):  # rows in blocks: bounded memory
        k = np.arange(lo, min(lo + 256, n))
        idx = np.clip(k[:, None] + offsets, 0, n - 2)
        w = pa[k][:, None, :] - a[idx]
        t = np.einsum("ijk,ijk->ij", w, d[idx])
        t = np.divide(t, l2[idx], out=np.zeros_like(t), where=l2[idx] > 0.0)
        r = w - np.clip(t, 0.0, 1.0)[..., None] * d[idx]
        out[k] = np.sqrt(np.einsum("ijk,ijk->ij", r, r).min(axis=1))
    return out


def replay(machine, pd, vd, kp, kf):
    """Replay gains on every axis of the machine and compute the contour error.

    Parameters
    ----------
    machine : dict
        The machine file (tomllib).
    pd, vd : ndarray, shape (N, 3)
        Setpoint positions (m) and velocities (m/s).
    kp, kf : ndarray, shape (N, 3)
        Gains per sample and axis ((m/min)/mm, 1).

    Returns
    -------
    dict
        ``pos`` (N, 3), ``u`` (N, 3), ``ce`` (N,).
    """
    pos, u = np.empty_like(pd), np.empty_like(pd)
    for c, a in enumerate(AXES):
        pos[:, c], u[:, c] = replay_axis(
            machine["axes"][a]["cascade"], machine["timing"], pd[:, c], vd[:, c], kp[:, c], kf[:, c]
        )
    return {"pos": pos, "u": u, "ce": contour_error(pd, pos)}


def eq2_ratios(u: np.ndarray, te: float, limits: dict) -> np.ndarray:
    """Peaks of |u|, |du|/Te, |d2u|/Te^2 of one axis over the limits (paper eq. 2).

    Parameters
    ----------
    u : ndarray, shape (N,)
        Velocity commands, m/s; the axis is at rest (u = 0) before sample 0.
    te : float
        Sample period, s.
    limits : dict
        The axis's ``limits`` table of the machine file.

    Returns
    -------
    ndarray, shape (3,)
        Velocity, acceleration and jerk ratios; <= 1 within the limits.
    """
    up = np.concatenate([[0.0, 0.0], u])
    peaks = (
        np.abs(u).max(),
        (np.abs(np.diff(up)) / te)[1:].max(),
        (np.abs(up[2:] - 2.0 * up[1:-1] + up[:-2]) / te**2).max(),
    )
    return np.array(peaks) / [limits["vmax_m_s"], limits["amax_m_s2"], limits["jmax_m_s3"]]


def mse(ce: np.ndarray) -> float:
    """Mean square of the contour error over the feed samples, m^2.

    Every sample of short_xz is a feed sample (oga counts ``~setpoints.rapid``,
    oga/verify/replay.py, and the program has no G0: :func:`test_every_sample_is_a_feed_sample`).
    """
    return float(np.mean(ce * ce))


def rel(a: float, b: float) -> float:
    """Relative difference ``|a - b| / |b|``."""
    return abs(a - b) / abs(b)


# --- tests -------------------------------------------------------------------------------


def test_every_sample_is_a_feed_sample(outputs):
    text = re.sub(r"\([^)]*\)|;.*", "", PROGRAM.read_text())
    assert not re.search(r"\bG0*0(?![0-9.])", text, flags=re.IGNORECASE)  # no rapid (G0)
    summ = outputs["summary"]
    assert summ["samples"] == len(outputs["table"]["t_s"]) == len(outputs["plan"]["x_pos_m"])
    assert summ["toolpath_sha256"] == hashlib.sha256(PROGRAM.read_bytes()).hexdigest()
    assert summ["status"] == "ok" and summ["limits_ok"] and not summ["kept_baseline"]


def test_table_columns_and_setpoints(outputs, machine):
    tab = outputs["table"]
    names = ["t_s", "s_m"] + [
        f"{a}_{c}" for a in AXES for c in ("pos_m", "vel_m_s", "kp_m_min_per_mm", "kf")
    ]
    assert list(tab) == names
    te = machine["timing"]["te_s"]
    n = len(tab["t_s"])
    np.testing.assert_allclose(tab["t_s"], np.arange(n) * te, rtol=0, atol=1e-12)
    # the table's setpoints are exactly what `oga plan` writes
    for a in AXES:
        for c in ("pos_m", "vel_m_s"):
            np.testing.assert_array_equal(tab[f"{a}_{c}"], outputs["plan"][f"{a}_{c}"])
    # and the velocity column is the centred difference of the positions (at rest
    # before and after), to rounding
    pos, vel = setpoint_arrays(tab)
    pp = np.concatenate([pos[:1], pos, pos[-1:]])
    np.testing.assert_allclose(vel, (pp[2:] - pp[:-2]) / (2 * te), rtol=0, atol=1e-12)
    assert np.abs(vel[:, 1]).max() == 0.0 and np.ptp(pos[:, 1]) == 0.0  # Y stands still


def test_replayed_ratio_and_figures_match_the_summary(outputs, replays):
    summ = outputs["summary"]
    opt, base = replays["opt"]["ce"], replays["base"]["ce"]
    ratio = mse(opt) / mse(base)
    diffs = {
        "ratio_mse": rel(ratio, summ["ratio_mse"]),
        "base mse": rel(mse(base) * 1e12, summ["baseline"]["mse_ce_um2"]),
        "opt mse": rel(mse(opt) * 1e12, summ["optimized"]["mse_ce_um2"]),
        "base rms": rel(math.sqrt(mse(base)) * 1e6, summ["baseline"]["rms_ce_um"]),
        "opt rms": rel(math.sqrt(mse(opt)) * 1e6, summ["optimized"]["rms_ce_um"]),
        "base max": rel(base.max() * 1e6, summ["baseline"]["max_ce_um"]),
        "opt max": rel(opt.max() * 1e6, summ["optimized"]["max_ce_um"]),
        "base p95": rel(np.percentile(base, 95) * 1e6, summ["baseline"]["p95_ce_um"]),
        "opt p95": rel(np.percentile(opt, 95) * 1e6, summ["optimized"]["p95_ce_um"]),
    }
    for which, key in (("base", "baseline"), ("opt", "optimized")):  # following error
        lag = np.abs(replays["pd"] - replays[which]["pos"]).max(axis=0) * 1e6
        for c, a in enumerate(AXES):
            if lag[c] > 0.0:
                diffs[f"{which} track {a}"] = rel(lag[c], summ[key]["track_max_um"][a])
            else:  # an axis that stands still
                assert summ[key]["track_max_um"][a] == 0.0
    print({k: f"{v:.1e}" for k, v in diffs.items()})
    assert max(diffs.values()) <= RTOL, diffs
    assert ratio < 0.2  # the schedule really cuts the error (0.095 today)


def test_replayed_commands_meet_eq2(outputs, machine, replays):
    te = machine["timing"]["te_s"]
    summ = outputs["summary"]["command_ratio_to_limits"]
    for which in ("opt", "base"):
        u = replays[which]["u"]
        for c, a in enumerate(AXES):
            r = eq2_ratios(u[:, c], te, machine["axes"][a]["limits"])
            assert np.all(r <= 1.0), (which, a, r)
            if which == "opt" and a in summ:  # the summary's figures, to rounding
                expected = [summ[a][q] for q in ("v", "a", "j")]
                np.testing.assert_allclose(r, expected, rtol=RTOL)


@pytest.mark.parametrize("factor", [1.3, 1.001])
def test_a_corrupted_table_is_caught(outputs, machine, replays, factor):
    tab, summ = outputs["table"], outputs["summary"]
    pd_, vd = setpoint_arrays(tab)
    kp = np.stack([tab[f"{a}_kp_m_min_per_mm"] for a in AXES], axis=1)
    kf = np.stack([tab[f"{a}_kf"] for a in AXES], axis=1)
    kp[300:600, 0] *= factor  # X's Kp too high over 0.3 s of the contour
    bad = replay(machine, pd_, vd, kp, kf)
    ratio = mse(bad["ce"]) / mse(replays["base"]["ce"])
    print(f"Kp x {factor}: ratio {ratio:.6f} vs {summ['ratio_mse']:.6f}")
    # moved far beyond the tolerance (1.3: to 1.82; 1.001: by 3e-4 relative)
    assert rel(ratio, summ["ratio_mse"]) > 1e4 * RTOL
