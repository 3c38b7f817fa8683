"""Every default of the project, in one place (SI unless the name says otherwise)."""

from __future__ import annotations

__all__ = [
    "DT_S",
    "TOL_M",
    "NP",
    "LAMBDA",
    "ANCHOR",
    "A1",
    "A2",
    "CE_WINDOW_SAMPLES",
]

#: Position-loop / interpolation period Te, seconds.
DT_S = 1e-3
#: Interpolation tolerance (largest deviation of a setpoint from the programmed path), metres.
TOL_M = 20e-6
#: Prediction horizon of the receding-horizon search, samples (paper: 50).
NP = 50
#: Weight of the gain increment in the cost (paper: 0.01).
LAMBDA = 0.01
#: Weight pulling the adjusted gains back to the baseline (0: the paper's cost), um^2 per unit^2.
ANCHOR = 0.0
#: Candidate fractions of the admissible increment interval (paper: a1 = 0.01, a2 = 0.05).
A1 = 0.01
A2 = 0.05
#: Half-width of the index window searched for the contour error around each sample, in
#: moving samples (standstill not counted). Must exceed the tracking lag in samples,
#: (1 - Kf) / (Kp Te) plus dead time and velocity-loop lag: about 70 at Kp 1 (m/min)/mm, Kf 0.
CE_WINDOW_SAMPLES = 150
