"""Gain-table exports: CSV/JSON/NPZ/C carry exactly the same float64 values and the metadata."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import subprocess

import numpy as np
import pytest

from feedplan.setpoints import AXES
from oga.errors import OptimizeError, OptionError
from oga.export.table import (
    TABLE_FORMATS,
    gain_table,
    render_table,
    table_c_header,
    table_columns,
    table_csv,
    table_from_npz,
    table_json,
    table_npz,
)
from oga.model.machine import load_machine
from oga.options import options_from_dict
from oga.pipeline import run_job

#: A short XZ contour (line, arc, line; about 1 s of motion at F3000).
PROGRAM = "G21 G90 G18\nG1 X0 Z0 F3000\nG1 X8\nG2 X13 Z5 I0 K5\nG1 X25 Z5\nM2\n"
#: A name that needs escaping in a C string literal.
SOURCE = 'we"ird\\ n\u00e4me??=.ngc'


@pytest.fixture(scope="module")
def job():
    job = run_job(PROGRAM, "gcode", load_machine("ucp710"), options_from_dict({"nominal": True}),
                  source=SOURCE)
    assert job.result.status == "ok", job.result.optimized.violations
    return job


def _columns(job):
    header, cols = table_columns(job.result)
    return header, np.column_stack(cols)


def test_csv_of_a_detached_table_is_byte_identical(job):
    table = table_from_npz(table_npz(job.result))
    assert render_table(table, "csv").decode() == table_csv(job.result)


def test_npz_round_trips_every_value_exactly(job):
    header, data = _columns(job)
    table = table_from_npz(table_npz(job.result, toolpath_sha256="abc"))
    assert table.header == tuple(header)
    assert np.array_equal(table.data, data)
    assert table.meta["toolpath_sha256"] == "abc"


def test_json_holds_columns_and_metadata(job):
    header, data = _columns(job)
    digest = hashlib.sha256(PROGRAM.encode()).hexdigest()
    doc = json.loads(table_json(job.result, toolpath_sha256=digest))
    assert list(doc["columns"]) == header
    for j, c in enumerate(header):
        assert np.array_equal(np.array(doc["columns"][c]), data[:, j])
    meta = doc["meta"]
    assert meta["toolpath_sha256"] == job.toolpath_sha256 == digest
    assert meta["machine_sha256"] == load_machine("ucp710").digest()
    assert meta["toolpath"] == SOURCE
    assert meta["sample_period_s"] == 1e-3
    assert meta["samples"] == len(job.setpoints) == data.shape[0]
    assert meta["axes"] == list(AXES)
    assert meta["units"]["x_kp_m_min_per_mm"] == "(m/min)/mm"
    assert meta["units"]["z_vel_m_s"] == "m/s"
    assert meta["units"]["t_s"] == "s" and meta["units"]["y_pos_m"] == "m"
    assert meta["units"]["x_kf"] == "1"


def test_a_failed_schedule_is_never_exported(job):
    failed = dataclasses.replace(job.result, status="failed")
    for export in (table_csv, table_json, table_npz, table_c_header):
        with pytest.raises(OptimizeError, match="failed verification"):
            export(failed)


def test_unknown_format_and_bad_c_name_are_refused(job):
    table = gain_table(job.result)
    with pytest.raises(OptionError, match="format"):
        render_table(table, "xlsx")
    with pytest.raises(OptionError, match="C identifier"):
        table_c_header(job.result, name="1table")
    assert set(TABLE_FORMATS) == {"csv", "json", "npz", "c"}


_C_MAIN = r"""
#include <stdio.h>
#include <string.h>
#include "table.h"
int main(void) {
    printf("%d %.17g %d %s %zu %zu\n", TBL_SAMPLES, TBL_SAMPLE_PERIOD_S, TBL_AXES,
           TBL_AXIS_ORDER, strlen(TBL_MACHINE_SHA256), strlen(TBL_TOOLPATH_SHA256));
    printf("%s\n%s\n", TBL_TOOLPATH, TBL_MACHINE);
    for (int k = 0; k < TBL_SAMPLES; k++) {
        printf("%.17g %.17g", tbl_t_s[k], tbl_s_m[k]);
        for (int a = 0; a < TBL_AXES; a++)
            printf(" %.17g %.17g %.17g %.17g", tbl_pos_m[k][a], tbl_vel_m_s[k][a],
                   tbl_kp_m_min_per_mm[k][a], tbl_kf[k][a]);
        printf("\n");
    }
    return 0;
}
"""


def test_c_header_compiles_and_holds_the_exact_values(job, tmp_path):
    header, data = _columns(job)
    (tmp_path / "table.h").write_text(
        table_c_header(job.result, name="tbl", toolpath_sha256=job.toolpath_sha256),
        encoding="utf-8")
    (tmp_path / "main.c").write_text(_C_MAIN)
    subprocess.run(["gcc", "-std=c11", "-Wall", "-Werror", "-pedantic", "-o", "main", "main.c"],
                   cwd=tmp_path, check=True, capture_output=True)
    out = subprocess.run([str(tmp_path / "main")], check=True, capture_output=True).stdout
    lines = out.decode("utf-8").splitlines()
    n, te, axes, order, mlen, tlen = lines[0].split()
    assert (int(n), float(te), int(axes), order) == (data.shape[0], 1e-3, 3, "xyz")
    assert int(mlen) == int(tlen) == 64
    assert lines[1] == SOURCE and lines[2] == "ucp710"
    got = np.array([[float(v) for v in line.split()] for line in lines[3:]])
    # C order: t, s, then per axis (pos, vel, kp, kf); the CSV order: per axis the same four
    assert np.array_equal(got, data)


def test_docs_library_example_runs_after_import_oga_alone(tmp_path, job):
    """The library example of the docs (Your first table, "From Python"), run as written in a
    fresh interpreter: ``import oga`` is enough for ``oga.export.table_csv(result)``, and no
    plotting or web module loads."""
    from pathlib import Path
    import sys

    root = Path(__file__).parents[1]
    page = root / "docs" / "tutorials" / "first-table.md"
    section = page.read_text().split("## From Python", 1)[1]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    program = tmp_path / "part.ngc"
    program.write_text(PROGRAM)
    code += ("import sys\n"
             "print(oga.export.table_csv(result).splitlines()[0])\n"
             "print(result.summary()['ratio_mse'] == result.ratio_mse)\n"
             "print(sorted(m for m in ('matplotlib', 'plotly', 'fastapi', 'uvicorn', 'oga.report.optimize')"
             " if m in sys.modules))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    status, header, same, loaded = r.stdout.splitlines()
    assert status.split()[0] == "ok" and 0 < float(status.split()[1]) < 1
    assert header == ",".join(table_columns(job.result)[0])
    assert same == "True" and loaded == "[]"


def test_oga_optimize_stays_the_function_whatever_loads_its_module_first():
    """``oga.optimize()``, ``oga.simulate()`` are functions with submodules of the same name: a
    submodule loaded first (by ``oga.run_job`` or ``import oga.pipeline``) must not take
    the function's place."""
    import sys

    code = ("import oga\n"
            "oga.run_job\n"
            "import oga.pipeline, oga.optimize, oga.model.simulate\n"
            "print(oga.optimize.__module__, oga.optimize.__name__, oga.simulate.__name__)\n"
            "from oga import optimize\n"
            "print(callable(optimize), sorted(set(dir(oga)) & {'export', 'optimize'}))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["oga.optimize optimize simulate",
                                     "True ['export', 'optimize']"]
