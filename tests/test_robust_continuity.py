"""The robust search's result changes little when the machine changes little (issue 28: an
identified machine with X's Kv scaled by 0.9999 gave a table of predicted ratio 0.362, by
1.0001 one of 0.029).

The lean part of ``bench/bench_perturb.py``: reference_xz on ucp710 with X's ``kv_n_s_m`` scaled
by 1 -+ 1e-4 and 1 -+ 1e-3 (its uncertainty set kept, so every plant of the set scales with
it). The certificate's median, p90 and worst ratio and the table's ratio on the machine itself
stay within :data:`BAND` (relative) of the unperturbed machine's. Measured over the bench's
sweep (every cascade value of both axes, bench/bench_perturb.py): reference_xz within 9.1 %,
helix_r20 within 1 % (docs/explanation/certificate.md); the band leaves room for the compiler
and CPU (the rounds' discrete choices move the figures in steps of about 5 %). freeform_xz and
cncjs_toolpath: one or two machines each where a round's choice once made the figures jump.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

import references
from oga.model.machine import load_machine
from oga.search.robust.search import robust_optimize

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_perturb import figures, scaled  # noqa: E402

#: Largest relative departure of each figure from the unperturbed machine's.
BAND = 0.15


NAME = "reference_xz.ngc"


@pytest.fixture(scope="module")
def unperturbed():
    sp = references.robust_setpoints(NAME)
    return sp, references.robust_case(NAME, sp)


@pytest.fixture(scope="module")
def reference(unperturbed):
    sp, rob = unperturbed
    return load_machine("ucp710"), sp, figures(rob)


@pytest.mark.portable
def test_the_robust_table_and_certificate_are_the_stored_ones(unperturbed):
    """The exported table, the baseline, the rounds and the certificate's ratio on every plant
    of reference_xz equal ``tests/data/reference/robust.npz`` within :data:`references.TOL`
    (what a refactor must keep: issue 31)."""
    got = references.robust_arrays(unperturbed[1])
    assert references.compare("robust", NAME, got) == []


@pytest.mark.parametrize("factor", [0.999, 0.9999, 1.0001, 1.001])
def test_a_small_change_of_kv_changes_the_robust_ratios_little(reference, factor):
    m, sp, ref = reference
    rob = robust_optimize(sp, scaled(m, "x", "kv_n_s_m", factor), threads=2)
    assert rob.status == "ok"
    got = figures(rob)
    for k, v in ref.items():
        assert abs(got[k] / v - 1.0) <= BAND, (k, got[k], v)


FREEFORM = "freeform_xz.ngc"
#: freeform_xz's bands (relative), per figure. Over bench/bench_perturb.py's sweep of X's Kv and
#: mass (x 1 -+ 1e-4 and 1 -+ 1e-3, 8 machines, 2026-11-28, every run 3 rounds since
#: oga.defaults.ROBUST_MIN_ROUNDS) the certificate's median moved by at most 2.4 % at 1e-4
#: (36.8 % at X's mass x 1.001, the one run outside bench_perturb's bands), worst 1.5 %, the ratio
#: on the machine itself (0.052) by 4.6 % at 1e-4. Where round 2 stopped at the goals on some
#: machines and went on elsewhere, the median moved by 36 % and that ratio by 64 % at 1e-4.
FREEFORM_BAND = {"median": 0.1, "p90": 0.1, "worst": 0.1, "nominal": 0.3}


@pytest.fixture(scope="module")
def freeform():
    sp = references.robust_setpoints(FREEFORM)
    return load_machine("ucp710"), sp, figures(references.robust_case(FREEFORM, sp))


@pytest.mark.parametrize("axis, field, factor", [("x", "kv_n_s_m", 1.0001),
                                                 ("z", "kv_n_s_m", 1.001)])
def test_a_round_whose_search_collapsed_is_searched_again(freeform, axis, field, factor):
    """freeform_xz: on these machines round 3's window search collapses (median ratio 5.5-6.5,
    Kf trapped low) at a reserve where ucp710's does not; its plant was dropped and the
    table's worst ratio jumped 0.639 -> 0.742, its ratio on the machine 0.055 -> 0.129. The
    round is now searched again at a lower reserve
    (:func:`oga.search.robust.search._retried`) and the figures stay with ucp710's."""
    m, sp, ref = freeform
    rob = robust_optimize(sp, scaled(m, axis, field, factor), threads=2)
    assert rob.status == "ok"
    got = figures(rob)
    for k, v in ref.items():
        assert abs(got[k] / v - 1.0) <= FREEFORM_BAND[k], (k, got[k], v)


CNCJS = "cncjs_toolpath.nc"


def test_a_round_where_the_rounds_stall_is_searched_at_a_raised_reserve():
    """cncjs_toolpath: Z's Kv x 1.001 moves round 1's peak on an unsearched corner 1.3060 ->
    1.3425, so round 2 runs at reserve 0.7303 (0.7507 on ucp710), where its figures are worse
    (worst 0.917 against 0.717), and the rounds stalled there (the next would repeat it). The
    stalled best round is now searched once more at its reserve raised by the margin
    (:func:`oga.search.robust.search._stalls_best`) and the figures stay within 10 % of
    ucp710's: measured 1.4-3.1 % (43 of the sweep's 45 runs were within 4.9 % before; these two
    left by 12-28 %, every figure above 10 %)."""
    m, sp = load_machine("ucp710"), references.robust_setpoints(CNCJS)
    ref = figures(robust_optimize(sp, m, threads=2))
    rob = robust_optimize(sp, scaled(m, "z", "kv_n_s_m", 1.001), threads=2)
    assert rob.status == "ok"
    got = figures(rob)
    for k, v in ref.items():
        assert abs(got[k] / v - 1.0) <= 0.1, (k, got[k], v)
