"""Robust schedules over a machine's uncertainty set.

- :mod:`oga.robust.plants`: concrete plants drawn from the set (Monte Carlo and corners).
- :mod:`oga.robust.certificate`: a table and the fixed baseline replayed on every plant.
- :mod:`oga.robust.search`: prototype of the robust search (design machine, shrink, certificate).
"""
