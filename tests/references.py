"""Reference results kept as arrays, compared with measured tolerances (not by their hash).

A float result differs in its last bits from one computer to another: OpenBLAS picks its
kernels by CPU (``DYNAMIC_ARCH``: SkylakeX here, Haswell on AMD Zen), numpy dispatches its
ufuncs to the widest SIMD the CPU has, numba compiles for the host CPU. A SHA-256 of such a
result therefore pins one CPU, not the behaviour. This module computes the results the
suite keeps (setpoints of the planner, schedules of the nominal search, whole replays of
:func:`oga.verify.verify`), stores them in ``tests/data/reference/*.npz`` and compares them
with tolerances measured across configurations (:data:`CONFIGS`, ``spread`` below): each
tolerance sits a decade or more above the largest spread measured and far below what a real
change of behaviour moves (``docs/explanation/portability.md`` gives the figures).

Regenerate the arrays on purpose, from the repository root (a planner or search change that
is meant to change results; the commit says why)::

    PYTHONPATH=. python tests/references.py regen plan      # setpoints (the planner's)
    PYTHONPATH=. python tests/references.py regen search    # nominal schedules
    PYTHONPATH=. python tests/references.py regen verify    # replays
    PYTHONPATH=. python tests/references.py regen robust    # robust tables, certificates
    PYTHONPATH=. python tests/references.py regen all

``search`` and ``verify`` run on the setpoints of :mod:`pinned_setpoints` (fixed arrays), so a
planner change leaves them alone. Measure the spread across CPU configurations (one
subprocess per configuration; about 10 min of CPU)::

    PYTHONPATH=. python tests/references.py spread [plan|search|verify|all]
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "tests") not in sys.path:  # run as a script: the helpers beside it
    sys.path.insert(0, str(ROOT / "tests"))

import plan_reference  # noqa: E402
from pinned_setpoints import pinned_setpoints  # noqa: E402

FOLDER = ROOT / "tests" / "data" / "reference"
KINDS = ("plan", "search", "verify", "robust")

#: Programs whose nominal schedules are kept (full mode, default options, ucp710).
SEARCH_PROGRAMS = ("reference_xz.ngc", "short_xz.ngc", "corner_steps.ngc",
                   "sharp_corners_xy.ngc", "rapids_xy.ngc")
#: Every SEARCH_STRIDE-th sample of a schedule is kept (a change of the search moves many).
SEARCH_STRIDE = 4
#: Replays kept: plant 0 is ucp710, plant i its scenario_set(ucp710, 64, seed 17).plants[i - 1]
#: (the linear friction setting unset: the exact kernel), reference_xz with wandering gains.
VERIFY_PLANTS = (0, 8, 40, 72, 96)
#: Programs whose robust table, baseline and certificate are kept (default options, ucp710).
ROBUST_PROGRAMS = ("reference_xz.ngc",)
#: Every VERIFY_STRIDE-th sample of a replay's positions, commands and contour error is kept.
VERIFY_STRIDE = 5

#: Tolerances ``(absolute, relative)`` per kind and float array (SI; gains in (m/min)/mm),
#: ``|got - stored| <= absolute + relative |stored|``, each a decade or more above the spread
#: measured across :data:`CONFIGS` and far below what a change of behaviour moves
#: (docs/explanation/portability.md, "Measured spread"). Arrays not named here (counts,
#: indices, flags, texts) compare exactly.
TOL = {
    "plan": {"pos": (1e-9, 0.0)},
    "search": {"kp": (1e-7, 0.0), "kf": (1e-7, 0.0)},
    "verify": {"pos": (1e-15, 0.0), "u": (1e-13, 0.0), "ce": (1e-15, 0.0),
               "command_ratio": (1e-13, 0.0), "ferror_ratio": (1e-13, 0.0),
               "max_dkp_per_sample": (1e-12, 0.0), "max_dkf_per_sample": (1e-12, 0.0),
               "metrics": (0.0, 1e-10)},
    "robust": {"kp": (1e-6, 0.0), "kf": (1e-6, 0.0), "baseline": (1e-6, 0.0),
               "alpha": (1e-6, 0.0), "reserve": (1e-8, 0.0), "ratio": (0.0, 1e-6),
               "nominal": (0.0, 1e-6)},
}

#: glibc's libm without its FMA/AVX2 variants (exp, sin, pow ... as on a CPU without them).
GLIBC_NO_FMA = "glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F"
#: Configurations the spread is measured over: the host as it is, and each source of
#: CPU-dependent rounding set to another CPU's choice (environment variables).
CONFIGS = {
    "host": {},
    "numba-generic": {"NUMBA_CPU_NAME": "generic"},
    "numba-opt0": {"NUMBA_OPT": "0"},
    "openblas-haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "openblas-sandybridge": {"OPENBLAS_CORETYPE": "Sandybridge"},
    "numpy-avx2": {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"},
    "glibc-no-fma": {"GLIBC_TUNABLES": GLIBC_NO_FMA},
    "all-generic": {"NUMBA_CPU_NAME": "generic", "OPENBLAS_CORETYPE": "Prescott",
                    "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
                    "GLIBC_TUNABLES": GLIBC_NO_FMA},
}


def _plan_case(name: str) -> dict:
    sp = plan_reference.plan_program(name)
    return {"samples": np.array(len(sp)), "block": sp.block, "rapid": sp.rapid,
            "pos": sp.pos[:: plan_reference.STRIDE]}


def search_arrays(result) -> dict:
    """What the suite keeps of an :class:`oga.optimize.OptimizeResult`: every
    :data:`SEARCH_STRIDE`-th row of the searched Kp and Kf, and whether the exported table is
    the searched one (bit for bit, in one process)."""
    s, e = result.searched_schedule, result.schedule
    same = (np.array_equal(s.kp_m_min_per_mm, e.kp_m_min_per_mm) and np.array_equal(s.kf, e.kf))
    return {"kp": s.kp_m_min_per_mm[::SEARCH_STRIDE], "kf": s.kf[::SEARCH_STRIDE],
            "exported_is_searched": np.array(same)}


def _search_case(name: str, mode: str = "full") -> dict:
    from oga.model.machine import load_machine
    from oga.optimize import optimize

    r = optimize(pinned_setpoints(name), load_machine("ucp710"), {"mode": mode, "nominal": True})
    return search_arrays(r)


def verify_gains(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample gains that wander inside the bounds (seeded random walks), shape (n, 3)."""
    rng = np.random.default_rng(seed)
    kp = np.clip(3 + np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0), 1, 5)
    kf = np.clip(0.8 + np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0), 0, 1)
    return kp, kf


def verify_plant(i: int):
    """Plant ``i`` of :data:`VERIFY_PLANTS` (the exact kernel: no linear friction setting)."""
    from oga.model.machine import load_machine
    from oga.search.robust.plants import scenario_set

    ucp = load_machine("ucp710")
    plant = ucp if i == 0 else scenario_set(ucp, n=64, seed=17).plants[i - 1]
    return plant.model_copy(update={"timing": plant.timing.model_copy(
        update={"friction_linear_below_m_s": None})})


def _verify_case(i: int) -> dict:
    from oga.verify.replay import verify

    sp = pinned_setpoints("reference_xz.ngc")
    kp, kf = verify_gains(len(sp))
    v = verify(sp, verify_plant(i), kp, kf, {a: (1.0, 5.0) for a in "xz"})
    m = v.metrics
    s = VERIFY_STRIDE
    return {"pos": v.pos[::s], "u": v.u[::s], "ce": v.ce[::s], "command_ratio": v.command_ratio,
            "ferror_ratio": v.ferror_ratio, "max_dkp_per_sample": v.max_dkp_per_sample,
            "max_dkf_per_sample": v.max_dkf_per_sample,
            "metrics": np.array([m.mse_m2, m.rms_m, m.max_abs_m, m.p50_m, m.p95_m, m.p99_m,
                                 *m.track_max_m, *m.track_rms_m]),
            "n": np.array(m.n), "ok": np.array(v.ok),
            # what broke, where: the ratio's digits left to command_ratio (a tolerance)
            "violations": np.array([re.sub(r"\d+\.\d+x its limit", "#x its limit", t)
                                    for t in v.violations], dtype=str)}


def robust_arrays(rob) -> dict:
    """What the suite keeps of a :class:`oga.search.robust.search.RobustResult`: its status, the
    robust baseline (Kp, Kf), every :data:`SEARCH_STRIDE`-th row of the exported table, the
    kept shares and reserve, the rounds, the certificate's per-plant MSE ratio, and the
    nominal MSE/RMS/max of the table and the baseline (the summary's figures)."""
    res, c = rob.result, rob.certificate
    m_o, m_b = res.optimized.metrics, res.baseline.metrics
    return {"status": np.array(rob.status), "certificate": np.array(c.status),
            "baseline": np.array([rob.baseline.kp, rob.baseline.kf]),
            "kp": rob.schedule.kp_m_min_per_mm[::SEARCH_STRIDE],
            "kf": rob.schedule.kf[::SEARCH_STRIDE],
            "alpha": np.asarray(rob.alpha, dtype=float), "reserve": np.array(rob.reserve),
            "rounds": np.array(rob.rounds), "ratio": np.asarray(c.ratio),
            "nominal": np.array([m_o.mse_m2, m_o.rms_m, m_o.max_abs_m,
                                 m_b.mse_m2, m_b.rms_m, m_b.max_abs_m])}


def robust_setpoints(name: str):
    """Program ``name`` of ``tests/data`` planned for ucp710 (tolerance 20 um): the robust
    reference and the continuity sweep share this run (a planner change regenerates ``robust``;
    the plan reference tells it apart)."""
    from feedplan.read import load_toolpath
    from oga.model.machine import load_machine
    from oga.pipeline import plan_toolpath

    m = load_machine("ucp710")
    return plan_toolpath(load_toolpath(ROOT / "tests" / "data" / name), m, feed_m_s=None,
                         tol_m=2e-5)


def robust_case(name: str, setpoints=None):
    """The robust search of program ``name`` (:func:`robust_setpoints`), ucp710, default
    options, two threads (the same bits on any number)."""
    from oga.model.machine import load_machine
    from oga.search.robust.search import robust_optimize

    sp = robust_setpoints(name) if setpoints is None else setpoints
    return robust_optimize(sp, load_machine("ucp710"), threads=2)


def cases(kind: str) -> dict:
    """Case name -> zero-argument function computing its arrays, for ``kind``."""
    if kind == "plan":
        return {n: (lambda n=n: _plan_case(n)) for n in plan_reference.PROGRAMS}
    if kind == "search":
        out = {n: (lambda n=n: _search_case(n)) for n in SEARCH_PROGRAMS}
        out["short_xz.ngc paper"] = lambda: _search_case("short_xz.ngc", "paper")
        return out
    if kind == "verify":
        return {f"plant {i}": (lambda i=i: _verify_case(i)) for i in VERIFY_PLANTS}
    if kind == "robust":
        return {n: (lambda n=n: robust_arrays(robust_case(n))) for n in ROBUST_PROGRAMS}
    raise ValueError(f"unknown kind {kind!r}; one of {', '.join(KINDS)}")


def path(kind: str) -> Path:
    return FOLDER / f"{kind}.npz"


def compute(kind: str) -> dict[str, np.ndarray]:
    """Every case of ``kind`` computed, flattened to ``{"<case>/<array>": array}``."""
    out = {}
    for case, fn in cases(kind).items():
        for key, arr in fn().items():
            out[f"{case}/{key}"] = np.asarray(arr)
    return out


def load(kind: str) -> dict[str, np.ndarray]:
    with np.load(path(kind)) as z:
        return {k: z[k] for k in z.files}


def stored(kind: str, case: str) -> dict[str, np.ndarray]:
    """The stored arrays of one case: ``{array: value}``."""
    pre = f"{case}/"
    return {k[len(pre):]: v for k, v in load(kind).items() if k.startswith(pre)}


def compare(kind: str, case: str, got: dict) -> list[str]:
    """What differs between ``got`` (a case's arrays) and the stored ones: arrays under
    :data:`TOL` by more than their tolerance (the largest difference named), every other
    array (counts, flags, indices, texts) exactly. Empty when they agree."""
    want = stored(kind, case)
    bad = []
    if set(want) != set(got):
        return [f"{case}: arrays {sorted(got)} against stored {sorted(want)}"]
    for key, ref in want.items():
        val = np.asarray(got[key])
        tol = TOL[kind].get(key)
        if val.shape != ref.shape:
            bad.append(f"{case}/{key}: shape {val.shape}, stored {ref.shape}")
        elif tol is None or val.dtype.kind not in "fc":
            if not np.array_equal(val, ref):
                where = np.flatnonzero(val.ravel() != ref.ravel())
                bad.append(f"{case}/{key}: {where.size} entries differ (first at flat index "
                           f"{where[0] if where.size else '-'})")
        else:
            atol, rtol = tol
            diff = np.abs(val - ref)
            excess = np.where(np.isnan(val) & np.isnan(ref), 0.0, diff - rtol * np.abs(ref))
            if not np.max(excess, initial=0.0) <= atol:  # NaN against a number fails too
                worst = float(np.max(np.where(np.isnan(excess), np.inf, diff), initial=0.0))
                bad.append(f"{case}/{key}: largest difference {worst:.3g} above the "
                           f"tolerance ({atol:g} + {rtol:g} relative)")
    return bad


def regen(kind: str) -> None:
    FOLDER.mkdir(parents=True, exist_ok=True)
    arrays = compute(kind)
    np.savez_compressed(path(kind), **arrays)
    print(f"wrote {path(kind)} ({path(kind).stat().st_size} bytes, {len(arrays)} arrays)")


#: ucp710's values as parsed (``model_dump(mode="json", exclude_none=True)``), stored when its
#: digest was 22ad1a24...: what a table made for ucp710 was made for. Some are derived by the
#: model (``kv_n_s_m``), so they are compared with :data:`VALUES_REL`, never by a hash.
UCP710_VALUES = FOLDER / "ucp710_values.json"
#: Relative tolerance of a stored machine value: a derived float's last bits, nothing more.
VALUES_REL = 1e-12


def ucp710_values() -> dict:
    """The stored values of ucp710 (:data:`UCP710_VALUES`)."""
    return json.loads(UCP710_VALUES.read_text())


def value_differences(got, want, where: str = "") -> list[str]:
    """Where two JSON-like trees differ: keys, types, strings exactly, numbers beyond
    :data:`VALUES_REL` of the stored one. Empty when they agree."""
    if isinstance(want, dict) and isinstance(got, dict):
        out = [f"{where}/{k}: missing or extra" for k in sorted(set(got) ^ set(want))]
        for k in sorted(set(got) & set(want)):
            out += value_differences(got[k], want[k], f"{where}/{k}")
        return out
    if isinstance(want, list) and isinstance(got, list) and len(got) == len(want):
        return [d for i, (g, w) in enumerate(zip(got, want))
                for d in value_differences(g, w, f"{where}[{i}]")]
    numbers = (int, float)
    if (isinstance(want, numbers) and isinstance(got, numbers)
            and not isinstance(want, bool) and not isinstance(got, bool)):
        ok = abs(got - want) <= VALUES_REL * abs(want)
    else:
        ok = type(got) is type(want) and got == want
    return [] if ok else [f"{where}: {got!r} != {want!r}"]


def _differences(a: dict, b: dict) -> dict[str, float]:
    """Per array name (without its case): the largest absolute difference over the cases;
    ``inf`` where a non-float array (count, flag, index) differs or a shape does."""
    out: dict[str, float] = {}
    for key, x in a.items():
        name = key.split("/", 1)[1]
        y = b[key]
        if x.shape != y.shape:
            d = np.inf
        elif x.dtype.kind in "fc":
            d = float(np.max(np.where(np.isnan(x) & np.isnan(y), 0.0, np.abs(x - y)), initial=0.0))
        else:
            d = 0.0 if np.array_equal(x, y) else np.inf
        out[name] = max(out.get(name, 0.0), d)
    return out


def spread(kinds=KINDS) -> dict:
    """Largest difference of every kept array between the host and each configuration of
    :data:`CONFIGS` (each computed in a subprocess with that environment): ``{kind: {config:
    {array: difference}}}``, printed as a table."""
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in kinds:
            runs = {}
            for name, env in CONFIGS.items():
                out = Path(tmp) / f"{kind}-{name}.npz"
                env = {**os.environ, **env, "PYTHONPATH": str(ROOT)}
                if "NUMBA_OPT" in env:  # numba's cache keys on the CPU, not on the level:
                    env["NUMBA_CACHE_DIR"] = str(Path(tmp) / name)  # compile afresh, apart
                subprocess.run([sys.executable, __file__, "_dump", kind, str(out)], check=True,
                               env=env)
                with np.load(out) as z:
                    runs[name] = {k: z[k] for k in z.files}
            result[kind] = {name: _differences(runs["host"], arrays)
                            for name, arrays in runs.items() if name != "host"}
            print(f"{kind}: largest difference to the host")
            names = sorted({k for d in result[kind].values() for k in d})
            print("  " + " ".join(f"{n:>14}" for n in ["config", *names]))
            for cfg, d in result[kind].items():
                print("  " + " ".join([f"{cfg:>14}"] + [f"{d[n]:14.3g}" for n in names]))
    return result


def main(argv: list[str]) -> int:
    if len(argv) >= 2 and argv[0] == "regen":
        for kind in KINDS if argv[1] == "all" else argv[1:]:
            regen(kind)
        return 0
    if argv and argv[0] == "spread":
        kinds = KINDS if len(argv) < 2 or argv[1] == "all" else tuple(argv[1:])
        json.dumps(spread(kinds))
        return 0
    if len(argv) == 3 and argv[0] == "_dump":  # one configuration's arrays (spread)
        np.savez(argv[2], **compute(argv[1]))
        return 0
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
