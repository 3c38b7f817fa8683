"""End to end identification from commands from another interpolator (trapezoidal velocity,
unlimited jerk, not our planner): the table made with the identified machine holds on the true
perturbed plant (tests/identify_e2e_cases.py; one case per file, so that xdist spreads them)."""

from tests.identify_e2e_cases import check_case


def test_identified_table_holds_on_the_true_plant_other_interpolator():
    check_case("other_interpolator")
