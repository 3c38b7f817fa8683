"""Every default of the project, in one place (SI unless the name says otherwise)."""

from __future__ import annotations

__all__ = [
    "DT_S",
    "TOL_M",
    "NP",
    "LAMBDA",
    "ANCHOR",
    "MPC_KNOT_SAMPLES",
    "MPC_WINDOW_INTERVALS",
    "MPC_COMMIT_INTERVALS",
    "MPC_ITERATIONS",
    "MPC_STOP",
    "MPC_TRUST",
    "MPC_RESTORE",
    "MPC_SETTLE_TAIL",
    "REPORT_MAX_POINTS",
    "MPC_MIN_NP",
    "MPC_SETTLED_M",
    "A1",
    "A2",
    "CE_WINDOW_SAMPLES",
    "API_HOST",
    "API_PORT",
    "API_MAX_UPLOAD_BYTES",
    "API_SYNC_MAX_MOTION_S",
    "API_SYNC_TIMEOUT_S",
    "BATCH_FORMATS",
    "BATCH_MAX_JOBS_PER_CPU",
    "DASK_CONNECT_S",
    "PG_CONNECT_S",
    "PG_POOL_MAX",
    "CCC_DEFAULTS",
    "CCC_TUNE_GRID",
    "ZPETC_CCC_DDOB_DEFAULTS",
    "ZPETC_CCC_DDOB_TUNE_GRID",
    "FUZZY_PID_KI_PER_KP2",
    "FUZZY_PID_KD",
    "FUZZY_PID_E_RANGE_M",
    "FUZZY_PID_EC_RANGE_M_S",
    "FUZZY_PID_TUNE_GRID",
    "SMC_DOB_CCC_DEFAULTS",
    "SMC_DOB_CCC_TUNE_GRID",
    "AFSMC_ERROR_SCALE_PER_LAG",
    "AFSMC_RATE_PER_OUTPUT_SCALE",
    "AFSMC_GAMMA_PER_KP_1_S",
    "AFSMC_TUNE_GAMMA_PER_KP_1_S",
    "AFSMC_TUNE_KP_COMP_PER_KP",
]

#: Position-loop / interpolation period Te, seconds.
DT_S = 1e-3
#: Interpolation tolerance (largest deviation of a setpoint from the programmed path), metres.
TOL_M = 20e-6
#: Prediction horizon per mode, samples: the paper's 50; full mode plans a window of 200
#: (its first two spline intervals are applied, the rest looks past them: an axis stopping
#: in the friction band settles over 300-500 ms, and the gains that matter act before the
#: stop).
NP = {"paper": 50, "full": 200}
#: Weight of the gain increments in the cost per mode, per unit^2 of increment (paper: 0.01),
#: against E'E in the mode's unit: mm^2 in paper mode (the paper's), um^2 in full mode
#: (there on the steps between the spline's control points).
LAMBDA = {"paper": 0.01, "full": 10.0}
#: Weight pulling the gains back to the baseline per mode, same units (paper: none).
ANCHOR = {"paper": 0.0, "full": 30.0}
#: Full mode: the planned gain trajectory (a quadratic B-spline) has control points
#: ``max(MPC_KNOT_SAMPLES, np // MPC_WINDOW_INTERVALS)`` samples apart.
MPC_KNOT_SAMPLES = 10
MPC_WINDOW_INTERVALS = 10
#: Full mode: spline intervals of each plan applied before the window recedes and is
#: planned again (at most half the window's intervals, at least one).
MPC_COMMIT_INTERVALS = 2
#: Full mode: sequential-QP iterations per window at most (each re-linearised on the plan).
MPC_ITERATIONS = 3
#: Full mode: an iteration that lowers the window's exact cost by less than this share ends
#: the window's iterations.
MPC_STOP = 0.05
#: Full mode: trust region of one iteration's control-point change, (m/min)/mm for Kp and 1
#: for Kf.
MPC_TRUST = (0.3, 0.05)
#: Full mode: where no step of an iteration keeps eq. 2 over the whole window (a limit ahead
#: that the plan cannot yet meet), up to this many more iterations, each with a trust region
#: three times wider, restore feasibility before the window recedes.
MPC_RESTORE = 2
#: Full mode: where an adjusted axis's setpoint comes to rest inside the window, the window
#: looks this many samples further, the plan's last gains held there, so that the prediction
#: sees the axis settle after the stop (inside the friction band it settles over 300-500 ms,
#: and the gains before the stop decide that error).
MPC_SETTLE_TAIL = 100
#: Full mode: an axis whose setpoint stands still over the window keeps its gains once its
#: position is this close to the setpoint, m (before that, its gains still act on its
#: settling).
MPC_SETTLED_M = 20e-9
#: Full mode: shortest window accepted, samples (dead time plus the loop's settling).
MPC_MIN_NP = 40
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
#: ``oga batch --jobs`` at most this many worker processes per CPU (each holds the compiled
#: kernels and a program's arrays in memory; the work is CPU-bound).
BATCH_MAX_JOBS_PER_CPU = 4
#: ``oga batch --scheduler``: how long to wait for the Dask scheduler's answer, s.
DASK_CONNECT_S = 10.0
#: ``oga serve --db postgresql://...``: how long to wait for the database's answer, s.
PG_CONNECT_S = 10.0
#: ``oga serve --db postgresql://...``: connections to the database per process at most.
PG_POOL_MAX = 8
#: Report figures: points per drawn line at most (min/max buckets keep the peaks).
REPORT_MAX_POINTS = 2000

# --- comparison controllers (oga compare): design defaults (run with tune=False) and the
# tuning grids (tune=True: every combination simulated on the toolpath, the least MSE(CE)
# whose velocity command meets paper eq. 2 wins, as for the fixed-gain baseline) ----------
#: ccc: the compensator C, Kc (1/s) and Ki (1/s^2). Kc = 20 1/s raises the loop gain across
#: the path to about 1.5 times the best fixed Kp (2.4 to 3 (m/min)/mm = 40 to 50 1/s), still
#: inside the stable range of the plane loop (see tests); Ki = 0: the paper's constant gain.
CCC_DEFAULTS = {"cc_gain_1_s": 20.0, "cc_integral_1_s2": 0.0}
#: ccc: 21 runs; Kp and Kf stay at the best fixed gains.
CCC_TUNE_GRID = {
    "cc_gain_1_s": [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0],
    "cc_integral_1_s2": [0.0, 200.0, 800.0],
}
#: zpetc-ccc-ddob: CCC as ccc; the Q low-pass of the paper (3rd-order Butterworth, 30 Hz);
#: zeros with |z| < 0.95 cancelled (their cancelling poles decay within about 60 samples);
#: every part switched on.
ZPETC_CCC_DDOB_DEFAULTS = {
    **CCC_DEFAULTS,
    "q_cutoff_hz": 30.0,
    "q_order": 3,
    "accept_radius": 0.95,
    "zpetc": True,
    "dob": True,
    "friction": True,
}
#: zpetc-ccc-ddob: 12 runs, the CCC gain and the observer's bandwidth.
ZPETC_CCC_DDOB_TUNE_GRID = {"cc_gain_1_s": [0.0, 20.0, 40.0], "q_cutoff_hz": [10.0, 30.0, 60.0, 100.0]}
#: fuzzy-pid: initial integral gain K'i = this * K'p^2 (1/s^2; the PI zero a decade below the
#: crossover) and derivative gain K'd (the PD zero at 20 K'p, above the crossover).
FUZZY_PID_KI_PER_KP2 = 0.1
FUZZY_PID_KD = 0.05
#: fuzzy-pid: error and error-rate ranges mapped onto [-6, 6] (the order of the baseline's
#: tracking error on a contour at F3000 and of its rate), m and m/s.
FUZZY_PID_E_RANGE_M = 100e-6
FUZZY_PID_EC_RANGE_M_S = 1e-3
#: fuzzy-pid: 18 runs: K'p as fractions of the best fixed Kp, K'i in units of K'p^2, and the
#: input ranges as multiples of the defaults (wide ranges keep the inputs near ZO: the gains
#: then vary slowly enough for the jerk limit of paper eq. 2).
FUZZY_PID_TUNE_GRID = {
    "kp_factor": (0.8, 1.0),
    "ki_per_kp2": (0.0, 0.02, 0.1),
    "range_factor": (1.0, 10.0, 100.0),
}
#: smc-dob-ccc (units in the names; the reasons are in oga.controllers.smc_dob_ccc).
SMC_DOB_CCC_DEFAULTS = {
    "c_1_s": 40.0,
    "eta_1_s": 100.0,
    "k_switch_m_s2": 0.05,
    "phi_m_s": 1e-3,
    "dob": True,
    "l_dob_1_s": 100.0,
    "ccc": True,
    "kcp_1_s": 20.0,
    "kci_1_s2": 0.0,
    "kcd": 0.0,
    "eps_range_m": 10e-6,
    "eps_rate_range_m_s": 1e-3,
    "gamma_1_s": 1.0,
    "sigma_1_s": 1.0,
}
#: smc-dob-ccc: 27 runs: surface pole, reaching gain, coupling gain.
SMC_DOB_CCC_TUNE_GRID = {
    "c_1_s": [20.0, 40.0, 80.0],
    "eta_1_s": [50.0, 100.0, 200.0],
    "kcp_1_s": [0.0, 20.0, 40.0],
}
#: afsmc (no table of the paper gives them), relative to the baseline gains: fuzzy error
#: universe edge (the input saturates beyond it) over the P-only following error v_prog / Kp
#: at the programmed feed: the initial surface is then linear over every error a P + FFW loop
#: makes (a 1 mm edge saturated on mcv-op at F8000 and the loop oscillated: jerk 31x the limit).
AFSMC_ERROR_SCALE_PER_LAG = 1.0
#: afsmc: change-rate universe edge over the output scale: the rate rules then add at most 0.1
#: of de/dt to the command (with 1.0 the derivative action alone broke the jerk limit, 1.03x).
AFSMC_RATE_PER_OUTPUT_SCALE = 10.0
#: afsmc: adaptation rate over the baseline Kp (1/s): gamma = this * Kp, 1/s^2 (adapts in
#: about 1/this s).
AFSMC_GAMMA_PER_KP_1_S = 1.0
#: afsmc: 15 runs: adaptation rates over Kp (1/s), and compensation gains over Kp.
AFSMC_TUNE_GAMMA_PER_KP_1_S = (0.01, 0.1, 1.0)
AFSMC_TUNE_KP_COMP_PER_KP = (0.05, 0.1, 0.25, 0.5, 1.0)
#: LinuxCNC export (``oga export --format linuxcnc``): machine units, the
#: ``pid.N.error-previous-target`` setting (TRUE: LinuxCNC 2.9's default, the motion
#: controller's convention), the HAL thread the files join, and the longest table streamed
#: (rows; the streamer's FIFO holds the whole table, 8 bytes per value, in shared memory).
LINUXCNC = {"units": "mm", "error_previous_target": True, "thread": "servo-thread",
            "max_rows": 4_000_000}
__all__ += ["LINUXCNC"]
#: LinuxCNC production tables (``oga export --recording``): the gains leave the table for the
#: fixed baseline once the motion controller's commanded joint position differs from the
#: recorded row by more than ``pos_tol_m`` (m; LinuxCNC repeats a program's commands to about
#: 1e-14 mm from the same start), or its trajectory speed ``motion.current-vel`` by more than
#: ``vel_tol_m_s`` (m/s; a feed override, feed hold or pause changes it in the first servo
#: period by about acceleration x period, 1 mm/s at 1 m/s^2 and 1 ms), or the feed or rapid
#: override leaves 1 by more than ``override_tol``. The feeder refills the stream every
#: ``feeder_poll_s`` seconds at most once the program is idle after a run.
LINUXCNC_MOTION = {"pos_tol_m": 1e-6, "vel_tol_m_s": 1e-6, "override_tol": 1e-6,
                   "feeder_poll_s": 0.02}
#: ``oga lcnc-record``: longest LinuxCNC start (s, until the machine is on and idle), longest
#: run of the program (s), servo periods recorded before the sampler's FIFO must be read
#: (the display reads it every few ms), and the runs of the program that must give the same
#: commands (LinuxCNC's planner starts a program differently when its task queues the next
#: moves late: measured on a loaded 2-core host, about one start in 15; a table follows one
#: motion only); and the shortest standstill between two motions that splits the program
#: into parts (servo periods): LinuxCNC's task times its non-motion commands between two
#: motions (tool change M6, pause M0/M1, spindle M3-M5, dwell G4; each takes well over 20 ms),
#: so no two runs repeat such a stop to the period; the planner's own standstills (exact-stop
#: corners, a drill cycle's reversals) last a period or two and repeat exactly.
LINUXCNC_RECORD = {"start_timeout_s": 60.0, "run_timeout_s": 3600.0, "fifo_rows": 1_000_000,
                   "repeats": 2, "stop_min_periods": 20}
__all__ += ["LINUXCNC_MOTION", "LINUXCNC_RECORD"]
#: ``--setpoints``: relative slack on the axis limits a recorded setpoint's finite differences
#: (velocity, acceleration, jerk) may reach before the file is refused (float64 rounding of
#: the positions, not a tolerance on the limits).
SETPOINTS_LIMIT_SLACK = 1e-6
__all__ += ["SETPOINTS_LIMIT_SLACK"]

# --- service bounds (oga serve: what one job may use) -----------------------------------------
#: CPU time one attempt of a job may use (RLIMIT_CPU of its worker), s; the job fails beyond.
API_JOB_CPU_S = 1800.0
#: Resident memory of the worker running a job (the engine itself takes about 250 MB), bytes;
#: the job fails beyond.
API_JOB_MEMORY_BYTES = 4 * 1024**3
#: A running job whose progress has not moved for this long marks /healthz "degraded", s.
API_STALL_S = 120.0


# --- G-code readers ------------------------------------------------------------------------
#: The G-code readers (``--reader``): the built-in one, LinuxCNC's interpreter (package
#: linuxcnc-uspace), or the built-in one and LinuxCNC's for the programs it does not read.
GCODE_READERS = ("auto", "builtin", "linuxcnc")
#: The default reader.
GCODE_READER = "auto"
#: Folder holding LinuxCNC's Python module ``gcode`` (Debian's linuxcnc-uspace).
LINUXCNC_PYTHON_PATH = "/usr/lib/python3/dist-packages"
#: Bounds of one run of LinuxCNC's interpreter on a program: wall time (an endless O-word loop
#: ends there), address space of its process, bytes.
LINUXCNC_READ_TIMEOUT_S = 120.0
LINUXCNC_READ_MEMORY_BYTES = 2 * 1024**3
__all__ += ["GCODE_READERS", "GCODE_READER", "LINUXCNC_PYTHON_PATH", "LINUXCNC_READ_TIMEOUT_S",
            "LINUXCNC_READ_MEMORY_BYTES"]


# --- input bounds ------------------------------------------------------------------------------
# What a user may submit: programs, options and machine files beyond these are refused with an
# error naming the limit and the value, before anything is allocated from them.
#: Largest |coordinate|, arc offset or radius of a program, metres (1 km).
MAX_COORD_M = 1e3
#: Largest toolpath file read, bytes (checked before reading: MAX_SEGMENTS moves of G-code
#: with generous comments fit well within it).
MAX_TOOLPATH_BYTES = 256 * 1024**2
#: Largest machine file read, bytes (a machine of ARX axes is a few kB).
MACHINE_MAX_BYTES = 16 * 1024**2
#: Largest gain table or summary ``oga export`` reads, bytes (a 4-hour table at 1 ms is about
#: 1 GB of CSV).
TABLE_MAX_BYTES = 2**31
#: Most lines of a G-code or CSV toolpath, and most arrays of a JSON one (checked before the
#: text is split or decoded; 8 lines per move of MAX_SEGMENTS).
MAX_TOOLPATH_LINES = 4_000_000
#: Most moves (segments) of one toolpath.
MAX_SEGMENTS = 500_000
#: Longest motion of one plan, seconds (estimated before planning, enforced while planning).
MAX_MOTION_S = 3600.0
#: Longest toolpath of POST /v1/jobs by default (`oga serve --job-max-motion-s`, at most
#: MAX_MOTION_S), seconds of motion: the planner's least motion time, estimated at submission
#: (413 beyond).
API_JOB_MAX_MOTION_S = MAX_MOTION_S
#: Most samples of one plan (the memory of the setpoints and of every replay grows with it).
MAX_SAMPLES = 4_000_000
#: Sample period (and machine Te) range, seconds.
DT_RANGE_S = (1e-5, 0.1)
#: Interpolation tolerance range, metres.
TOL_RANGE_M = (1e-7, 10e-3)
#: Plausible range (inclusive) of each numeric machine field, SI (the field's unit in its name;
#: gains in (m/min)/mm). A machine file outside them is refused naming the field.
MACHINE_FIELD_RANGES = {
    # limits
    "vmax_m_s": (1e-3, 20.0),
    "amax_m_s2": (1e-3, 1e3),
    "jmax_m_s3": (1e-2, 1e6),
    "ferror_max_m": (1e-7, 1.0),
    # cascade
    "mass_kg": (1e-2, 1e6),
    "coulomb_n": (0.0, 1e6),
    "static_n": (0.0, 1e6),
    "stribeck_m_s": (1e-7, 10.0),
    "viscous_n_s_m": (0.0, 1e8),
    "kv_n_s_m": (1e-12, 1e10),
    "tn_s": (1e-5, 100.0),
    "force_lag_s": (1e-7, 1.0),
    "force_limit_n": (1e-3, 1e15),
    "friction_smoothing_m_s": (1e-9, 1.0),
    # timing (a simulation setting: oga.model.machine.Timing)
    "friction_linear_below_m_s": (1e-9, 1e-3),
    # arx
    "arx_coefficient": (-1e6, 1e6),
    "arx_order": (1, 64),
    "coulomb_m_s": (0.0, 10.0),
    "viscous_ratio": (0.0, 100.0),
    "load_m_s_per_n": (0.0, 1.0),
    # G-code home positions and work offsets (oga.model.machine.Home), mm
    "position_mm": (-1e6, 1e6),
    # gains
    "kp_m_min_per_mm": (1e-3, 50.0),
    "kp_step_m_min_per_mm": (1e-2, 10.0),
    "kf": (0.0, 2.0),
    "kf_step": (1e-3, 1.0),
    "gm_min_db": (0.0, 60.0),
}


# identification ------------------------------------------------------------------------------
#: Longest trace read, rows (about 33 min at 1 kHz; a row costs about 100 bytes per channel).
TRACE_MAX_ROWS = 2_000_000
#: Largest file a trace reader opens, bytes.
TRACE_MAX_BYTES = 1 << 30
#: A sample period differing from the trace's median period by more than this share is
#: refused (non-uniform sampling); a step of over 1.5 periods is a gap, a step of 0 a duplicate.
TRACE_DT_REL_TOL = 1e-3
#: Speed above which a trace's positions are refused as absurd (a trace in mm read as metres),
#: m/s: no machine-tool axis moves at 20 m/s.
TRACE_MAX_SPEED_M_S = 20.0
#: Dead times searched by the fit, samples (0 .. this).
IDENT_MAX_DEAD_SAMPLES = 6
#: Multi-start: starting points of the friction parameters per dead time (Stribeck velocity
#: and static friction spread over their range).
IDENT_STARTS = 3
#: Confidence level of the intervals written beside the fitted values.
IDENT_CONFIDENCE = 0.95
#: Uncertainty section written by ``oga identify``: each factor range covers this many
#: confidence half-widths, and at least the floor below (the fit never pins a real machine
#: closer than that: the machine drifts with temperature, load and wear).
IDENT_UNCERTAINTY_WIDTHS = 2.0
IDENT_UNCERTAINTY_FLOOR = 0.05
#: ``oga excite``: feeds of the constant-speed passes as multiples of the base machine's
#: Stribeck velocity (inside and well above the band) and fractions of the axis speed limit.
EXCITE_STRIBECK_MULTIPLES = (0.3, 1.0, 3.0)
EXCITE_VMAX_FRACTIONS = (0.02, 0.1, 0.3, 0.6)
#: ``oga excite``: frequencies of the swept section, Hz (amplitude limited by acceleration).
EXCITE_SWEEP_HZ = (1.0, 2.0, 4.0, 7.0, 10.0, 15.0, 20.0)
#: ``oga excite``: default travel per axis, mm.
EXCITE_TRAVEL_MM = 100.0

# robust --------------------------------------------------------------------------------------
#: Monte Carlo plants drawn from a machine's uncertainty set (the certificate's sample).
ROBUST_MC_PLANTS = 64
#: Most Monte Carlo plants a certificate may ask for (``certify``; a bound at 95 % of 0.06 %).
ROBUST_MC_PLANTS_MAX = 5000
#: Seed of that draw (a certificate is reproducible).
ROBUST_SEED = 17
#: Level of the certificate's upper confidence bound on the share of the set's machines where
#: the table fails (oga.verify.certificate).
ROBUST_CONFIDENCE = 0.95
#: Groups of uncertain parameters whose set corners are added to the Monte Carlo plants, all
#: axes at the same end of their own ranges (2^groups corners): the parameters that move the
#: schedule's result (friction level, mass, Kv, Tn, dead time); the rest stay nominal.
ROBUST_CORNER_GROUPS = (("coulomb_n", "static_n"), ("mass_kg",), ("kv_n_s_m",), ("tn_s",),
                        ("dead_time_extra_samples",))
#: The scenario plants' simulation setting ``timing.friction_linear_below_m_s`` (m/s): below
#: it the kernel may take the friction as its tangent at rest over a period
#: (:class:`oga.model.machine.Timing`), which covers most periods of an axis standing still.
ROBUST_FRICTION_LINEAR_BELOW_M_S = 1e-6
#: ``timing.friction_linear_below_m_s`` at most this share of every cascade axis's
#: ``friction_smoothing_m_s`` and ``stribeck_m_s``: the tangent at rest is then the friction
#: within ``x^2 / 3 + x^2`` (1.3e-4) of it relative, ``x`` that share; far above it the
#: tangent is not the friction at all (tanh saturates, the Stribeck peak falls). The
#: scenario plants take the least of :data:`ROBUST_FRICTION_LINEAR_BELOW_M_S` and this share.
FRICTION_LINEAR_MAX_SHARE = 0.01
#: Robust search: rounds at most (each adds plants, and cuts the searched plants' limit
#: reserve where a table broke one); margin added to the first cut (doubled at each further cut).
ROBUST_ROUNDS = 5
ROBUST_RESERVE_MARGIN = 0.02
#: The rounds never stop at goals met before this one (:func:`oga.search.robust.search._next`):
#: round 2 meets them on some machines and breaks a limit on their 1e-4 neighbours (freeform_xz).
ROBUST_MIN_ROUNDS = 3
#: Robust search: bisection steps of the share of the searched schedule's departure from the
#: baseline kept where its certificate fails (oga.search.robust.search._shrink: to 1/128).
ROBUST_SHRINK_STEPS = 7
#: Robust search: the typical Monte Carlo plants the first round's schedule is screened on.
ROBUST_SUBSET = 8
#: Robust search: the Monte Carlo plants (the set's first) its rounds search and judge on,
#: with the corners; the kept table is certified on the whole set.
ROBUST_SEARCH_PLANTS = 64
#: Robust search: the anchors (:data:`ANCHOR`'s unit) searched again, in turn, where no share of
#: any round's table at the default anchor passes its certificate (and no anchor was given).
ROBUST_ANCHOR_RETRY = (3000.0,)
#: Robust search: the worst ratio a round aims for (with ROBUST_MEDIAN_GOAL, ROBUST_P90_GOAL).
ROBUST_WORST_GOAL = 0.9

# robust search -------------------------------------------------------------------------------
#: Multi-scenario search (:mod:`oga.search.robust.multi`): plants searched at once at most (the
#: nominal one included; the plants where the schedule did worst join it round by round).
ROBUST_ACTIVE = 4
#: Weight of the nominal plant in the window cost (the worst active plants share the rest).
ROBUST_NOMINAL_WEIGHT = 0.5
#: The certificate's median and 90th percentile of the MSE ratio a round aims for (with
#: ROBUST_WORST_GOAL): the rounds stop there.
ROBUST_MEDIAN_GOAL = 0.3
ROBUST_P90_GOAL = 0.5
#: Multi-scenario search: the least share of the baseline's own peak (eq. 2, following error)
#: on each searched plant that its limits keep, whatever the reserve (oga.search.robust.multi).
ROBUST_BASELINE_FLOOR = 0.85
#: Multi-scenario search: each searched plant's acceleration and jerk limits are at least its
#: baseline's own command at every sample, the largest within this many samples either side.
ROBUST_FLOOR_SAMPLES = 3
#: Robust search's repair (oga.search.robust.repair): the baseline held this long either side of
#: a sample where the table alone breaks a limit, s; the raised-cosine ramp back to the table,
#: s; the certificates it tries (each doubling both where the breaks stay in the faded stretch).
ROBUST_REPAIR_HOLD_S = 0.05
ROBUST_REPAIR_RAMP_S = 0.2
ROBUST_REPAIR_STEPS = 6
#: Robust baseline (:mod:`oga.search.robust.baseline`): the Monte Carlo plants whose geometric mean
#: MSE(CE) it minimises (the first ones of the set), and those of them its grid is screened
#: on; the refinement's steps at most, the step (in grid steps) below which it stops, and the
#: share of each limit its models keep clear of; the confirmations on every plant at most.
ROBUST_BASELINE_PLANTS = 32
ROBUST_BASELINE_GRID_PLANTS = 8
ROBUST_BASELINE_ITERATIONS = 30
ROBUST_BASELINE_TOL = 1e-2
ROBUST_BASELINE_GAIN = 5e-4
ROBUST_BASELINE_MARGIN = 1e-4
#: The corners at this share of a limit or more at the grid's best are modelled from the start
#: (critical). 0.95 gave the same baselines as 0.9 (every digit) on reference_xz,
#: circle_r50_f3000, freeform_xz, helix_r20, sharp_corners_xy, cam_pocket_xy and
#: cncjs_toolpath with 19-30 % fewer tangent replays (cncjs_toolpath 217 -> 165); 0.99 cost
#: reference_xz a second confirmation on every plant (273 replays).
ROBUST_BASELINE_SEED = 0.95
ROBUST_BASELINE_CONFIRMATIONS = 8

# corner blending -----------------------------------------------------------------------------
#: Share of the plan's tolerance given to corner blends (feedplan.blend; the rest is left to
#: the planner's filter, which rounds curves by about v^2 T^2 kappa / 24).
BLEND_TOL_FRACTION = 0.5
#: A corner is blended only where the speed estimated through its blend is at least this
#: share of the feed; below, an exact stop (planned exactly by ruckig) is as fast (measured on
#: ucp710 at F3000: a 20 deg kink blended at 0.17 F saves 2 %, a 45 deg one at 0.1 F loses 1 %).
BLEND_MIN_SPEED_SHARE = 0.15

# identify speed -------------------------------------------------------------------------------
#: Shortest interval between two progress reports of an identification fit, s.
IDENT_PROGRESS_EVERY_S = 0.5

# robust default ------------------------------------------------------------------------------
#: ``nominal`` option's default: False, the robust search (:mod:`oga.search.robust`) wherever the
#: machine has an uncertainty set (a machine without one is always searched nominally); True
#: searches the exact model only, as before issue 17.
NOMINAL = False

# identify start -------------------------------------------------------------------------------
#: Where the trace records the drive force, the fit starts from its friction: a regression of
#: the force over the samples moving faster than this (m/s; well above any Stribeck band).
IDENT_FORCE_REGRESSION_V_M_S = 0.01
#: The recorded force joins the fit's residual weighted by its noise, taken as at least this
#: share of its RMS (a drive's force carries model errors far above its sensor noise).
IDENT_FORCE_NOISE_SHARE = 0.01
#: A fit is ``poor`` where its position residual exceeds this many times the trace's noise,
#: or its force residual this share of the recorded force's RMS (100 bench draws of
#: bench/bench_identify.py: fits within the bounds 0.15-4.6 %, p95 1.2 %; the 3 out 7.7-28 %;
#: the position ratio separates nothing below 10: right fits up to 18.7, p95 1.16).
IDENT_POOR_NOISE_RATIO = 10.0
IDENT_POOR_FORCE_SHARE = 0.05

# identify model error --------------------------------------------------------------------------
#: Physical bounds of every parameter ``oga identify`` fits (the one place they are stated;
#: docs/explanation/identification.md). The solver never leaves them, and a fit that ends on
#: one is marked ``model-error``: a parameter pushed to a physical limit stands in for what the
#: model leaves out (a real speed loop fitted without them ran to viscous 470 000 N s/m and
#: Tn 0.6 ms). Forces, Kv and viscous friction per kg of the axis's mass (positions fix only
#: the ratios to the mass); dead time in position-loop samples.
IDENT_BOUNDS = {
    "velocity_loop_hz": (2.0, 300.0),  # Kv / (2 pi m), the velocity loop's bandwidth
    "tn_s": (2e-3, 1.0),  # the velocity PI's integral time
    "force_lag_s": (2e-5, 2e-3),  # the current loop (8 kHz .. 80 Hz) and what lags with it
    "coulomb_n_per_kg": (0.0, 10.0),  # Fc / m: a friction coefficient up to 1
    "stribeck_rise_n_per_kg": (0.0, 10.0),  # (Fs - Fc) / m
    "stribeck_m_s": (2e-5, 0.02),
    "viscous_1_s": (0.0, 50.0),  # B / m
    "mass_ratio": (1e-2, 1e2),  # identified mass / the base's (a recorded force)
    "dead_time_samples": (0.0, float(IDENT_MAX_DEAD_SAMPLES)),
}
#: A fit is marked ``model-error`` where its position residual exceeds this many times the
#: trace's noise (or a parameter ends on its bound): the model does not explain the trace,
#: and its uncertainty set is widened by the evidence (oga.identify.write).
IDENT_MODEL_ERROR_NOISE_RATIO = 2.0
#: Lags over which the residual's autocorrelation is summed (its correlation time, the
#: evidence of a residual that is not white), samples.
IDENT_CORRELATION_LAGS = 200
#: Each factor range of an identified axis covers at least this many times the larger of the
#: model-error share (the part of the velocity loop's imprint on the positions the model does
#: not predict) and the parameter's own model-error change, up to the largest relative
#: half-width below (oga.identify.write.uncertainty_of). Calibrated on two-mass drives (modes
#: at 45-70 Hz, semi- and full-closed; tests/test_two_mass.py): at 5 times a table's true
#: ratio on the plant fell outside its certificate (0.494 against a worst plant of 0.332), at
#: 10 inside (0.441 in [0.093, 0.636]).
IDENT_MODEL_ERROR_WIDTHS = 10.0
#: The most the model-error evidence widens a factor range, relative (+-50 %: an unmeasured
#: machine's friction in ucp710's assumed set); beyond, the fit is ``poor`` anyway.
IDENT_MODEL_ERROR_MAX_WIDTH = 0.5
#: Beyond this model-error share (or IDENT_POOR_NOISE_RATIO) the fit is ``poor``: the model
#: does not cover the plant, and a certificate on its set promises nothing on the machine.
IDENT_MODEL_ERROR_MAX_SHARE = 0.25
#: A fractional dead time is kept where it lowers the position residual's mean square by at
#: least this share below the best whole dead time's (measurably better).
IDENT_FRACTION_MIN_GAIN = 0.02

# gain laws (oga.law) --------------------------------------------------------------------------
#: Kinds of gain law (:mod:`oga.law.law`): Heidenhain MAC (Kp and Kf bilinear in |v| and |a|),
#: TwinCAT CNC dynamic Kv (Kp piecewise-linear in |v|, Kf constant), LinuxCNC lincurve (Kp and
#: Kf piecewise-linear in |v|; lincurve-sa: Kf in the signed acceleration a sign(v)).
LAW_KINDS = ("mac", "pl", "lincurve", "lincurve-sa")
#: Support points per input of each kind when not given (mac: per axis of its grid;
#: lincurve-sa: 8 kept half of the robust table's reduction on freeform_xz at 100 %, 6 not).
LAW_POINTS = {"mac": 3, "pl": 2, "lincurve": 4, "lincurve-sa": 8}
#: Largest support points per input of each kind (lincurve: the component's 16; TwinCAT's
#: dynamic Kv has exactly two; MAC's grid is kept small: its support points are typed in).
LAW_POINTS_MAX = {"mac": 5, "pl": 2, "lincurve": 16, "lincurve-sa": 16}
#: Feed overrides every law is searched and certified at (shares of the programmed feed).
LAW_OVERRIDES = (0.5, 0.8, 1.0, 1.2)
#: Override range accepted (LinuxCNC's default MAX_FEED_OVERRIDE is 1.2; a shop uses 0.5-1.2).
LAW_OVERRIDE_RANGE = (0.1, 2.0)
#: Rounds of the law search at most (the nominal plant, then the worst plants join).
LAW_ROUNDS = 5
#: Monte Carlo plants of the set the first round searches on besides the nominal one.
LAW_TYPICAL_PLANTS = 0
#: Gauss-Newton iterations per round at most, and the relative cost decrease that stops them.
LAW_ITERATIONS = 25
LAW_STOP = 1e-3
#: First trust region of a step: Kp ((m/min)/mm) and Kf.
LAW_TRUST = (0.3, 0.1)
#: Linearised eq. 2 rows per case, plant, axis and limit at most (local peaks of largest
#: ratio first; the exact replay of the line search checks every sample).
LAW_ROWS = 400
#: A sample's eq. 2 row joins the step's QP when its ratio may reach this share of its limit
#: within the trust region.
LAW_ROW_SHARE = 0.9
#: Shares of the searched law's departure from the baseline tried when no round certifies.
LAW_ALPHAS = (0.75, 0.5, 0.25)
#: The law's cost adds ``LAW_WORST_WEIGHT * max(0, ratio - LAW_WORST_RATIO)^2`` per searched
#: plant and case (:mod:`oga.law.search`): a weighted mean alone let one searched plant stay
#: above its baseline (helix_r20 at 50 % feed: worst 1.09-1.60 with up to 8 plants searched).
LAW_WORST_RATIO = 0.97
LAW_WORST_WEIGHT = 10.0
