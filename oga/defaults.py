"""Every default of the project, in one place (SI unless the name says otherwise)."""

from __future__ import annotations

__all__ = [
    "DT_S",
    "TOL_M",
    "NP",
    "LAMBDA",
    "ANCHOR",
    "MPC_ATTEMPTS",
    "MPC_ACCEPT_RATIO",
    "REPORT_MAX_POINTS",
    "MPC_MIN_NP",
    "MPC_REPLAN",
    "A1",
    "A2",
    "CE_WINDOW_SAMPLES",
    "API_HOST",
    "API_PORT",
    "API_MAX_UPLOAD_BYTES",
    "API_SYNC_MAX_MOTION_S",
    "API_SYNC_TIMEOUT_S",
    "BATCH_FORMATS",
]

#: Position-loop / interpolation period Te, seconds.
DT_S = 1e-3
#: Interpolation tolerance (largest deviation of a setpoint from the programmed path), metres.
TOL_M = 20e-6
#: Prediction horizon of the receding-horizon search, samples (paper: 50).
NP = 50
#: Weight of the gain increments in the cost per mode, per unit^2 of increment (paper: 0.01),
#: against E'E in the mode's unit: mm^2 in paper mode (the paper's), um^2 in full mode.
LAMBDA = {"paper": 0.01, "full": 100.0}
#: Weight pulling the gains back to the baseline per mode, same units (paper: none).
ANCHOR = {"paper": 0.0, "full": 300.0}
#: Full mode: the settings tried in turn, (move blocks over the horizon, trust region of a
#: block step in (m/min)/mm for Kp and 1 for Kf); the next is tried only when the previous
#: schedule did not reach MPC_ACCEPT_RATIO, and the best verified one is kept.
MPC_ATTEMPTS = ((10, 0.3, 0.05), (5, 0.1, 0.02))
#: Full mode: MSE(CE) ratio to the baseline that ends the attempts.
MPC_ACCEPT_RATIO = 0.8
#: Full mode: shortest horizon accepted, samples (dead time plus the loop's settling).
MPC_MIN_NP = 20
#: Full mode: samples between two plans (longer intervals were measured to lose the gain).
MPC_REPLAN = 1
#: Candidate fractions of the admissible increment interval (paper: a1 = 0.01, a2 = 0.05).
A1 = 0.01
A2 = 0.05
#: Half-width of the index window searched for the contour error around each sample, in
#: moving samples (standstill not counted). Must exceed the tracking lag in samples,
#: (1 - Kf) / (Kp Te) plus dead time and velocity-loop lag: about 70 at Kp 1 (m/min)/mm, Kf 0.
CE_WINDOW_SAMPLES = 150

# --- REST service (oga serve) and batch -------------------------------------------------------
#: Interface the server binds to (loopback only; the container binds 0.0.0.0 explicitly).
API_HOST = "127.0.0.1"
#: TCP port of the server.
API_PORT = 8000
#: Largest request body the server accepts, bytes (413 beyond it).
API_MAX_UPLOAD_BYTES = 16 * 1024 * 1024
#: Longest toolpath of POST /v1/gain-table, seconds of motion at the programmed feeds (413 beyond).
API_SYNC_MAX_MOTION_S = 10.0
#: Longest wait of POST /v1/gain-table for its job before it answers 202 (poll the job), s.
API_SYNC_TIMEOUT_S = 120.0
#: Table formats written by ``oga batch`` (names of oga.export.TABLE_FORMATS).
BATCH_FORMATS = ("csv",)
#: Report figures: points per drawn line at most (min/max buckets keep the peaks).
REPORT_MAX_POINTS = 2000
