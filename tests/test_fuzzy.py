"""The compiled fuzzy machinery against an independent numpy evaluation and hand results."""

from __future__ import annotations

import numpy as np
import pytest

from oga.controllers.fuzzy import DKD, DKI, DKP, LABELS, RULES, mamdani, memberships

CENTRES = np.arange(-6.0, 7.0, 2.0)
Y = np.linspace(-6.0, 6.0, 120_001)  # fine grid of the output universe


def _tri(x):
    """Membership of every label at the points ``x`` (7, len(x)), straight from the definition."""
    dist = np.abs(np.asarray(x, dtype=float)[None, :] - CENTRES[:, None])
    return np.clip(1.0 - dist / 2.0, 0.0, None)


def _reference(table, x_e, x_ec):
    """Mamdani min-max-centroid by brute force on a fine grid (the MATLAB recipe)."""
    me = _tri([np.clip(x_e, -6, 6)])[:, 0]
    mc = _tri([np.clip(x_ec, -6, 6)])[:, 0]
    out = _tri(Y)
    agg = np.zeros_like(Y)
    for i in range(7):
        for j in range(7):
            strength = min(me[i], mc[j])
            if strength > 0:
                agg = np.maximum(agg, np.minimum(strength, out[table[i, j] + 3]))
    return np.trapezoid(agg * Y, Y) / np.trapezoid(agg, Y)


def test_mamdani_matches_a_brute_force_centroid():
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.uniform(-7.5, 7.5, (80, 2)), [[0, 0], [6, -6], [-1, 3], [2, 2]]])
    for x_e, x_ec in points:
        for table in RULES:
            ref = _reference(table, x_e, x_ec)
            assert mamdani(table, x_e, x_ec) == pytest.approx(ref, abs=1e-7)


def test_single_rule_centroids_by_hand():
    # at (-6, -6) only the rule (NB, NB) fires, with strength 1: the output is its label's
    # triangle cut to [-6, 6]; PB: the half triangle on [4, 6] peaking at 6 -> 4 + 2 * 2/3
    assert LABELS[DKP[0, 0] + 3] == "PB"
    assert mamdani(DKP, -6.0, -6.0) == pytest.approx(16.0 / 3.0, abs=1e-12)
    assert mamdani(DKI, -6.0, -6.0) == pytest.approx(-16.0 / 3.0, abs=1e-12)
    # at (0, 0) only (ZO, ZO): Kd is NS, a whole triangle on [-4, 0], centroid -2
    assert LABELS[DKD[3, 3] + 3] == "NS"
    assert mamdani(DKD, 0.0, 0.0) == pytest.approx(-2.0, abs=1e-12)
    # half-way between two rules of equal consequent the output stays that label's centre
    assert mamdani(DKP, 1.0, 0.0) == pytest.approx(_reference(DKP, 1.0, 0.0), abs=1e-7)


def test_memberships_form_a_partition_of_unity():
    for x in np.linspace(-8, 8, 321):
        i, t = memberships(x)
        mu = _tri([np.clip(x, -6, 6)])[:, 0]
        expected = np.zeros(7)
        expected[i] += 1.0 - t
        expected[i + 1] += t
        np.testing.assert_allclose(mu, expected, atol=1e-12)


def test_tables_are_the_classic_ones():
    # the paper's printed first rules (e NL = NB): ec NB..PS -> (Kp, Ki, Kd)
    printed = [("PB", "NB", "PS"), ("PB", "NB", "NS"), ("PM", "NM", "NB"), ("PM", "NM", "NB"),
               ("PS", "NS", "NB")]
    for j, row in enumerate(printed):
        assert tuple(LABELS[t[0, j] + 3] for t in (DKP, DKI, DKD)) == row
    # the paper's tuning principles at zero error and rate: no Kp, Ki change
    assert DKP[3, 3] == 0 and DKI[3, 3] == 0
