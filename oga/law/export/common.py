"""What every law export states: the comment block saying what the certificate covers."""

from __future__ import annotations

from oga.law.search import LawResult

__all__ = ["certificate_lines"]


def certificate_lines(result: LawResult, machine_name: str, plants: int) -> list[str]:
    """The comment lines (without a comment prefix) of an export of ``result``."""
    cert = result.certificate
    lines = [
        f"oga gain law ({result.law.kind}), machine {machine_name!r}",
        f"status: {result.status}" + (
            f" (no law certified: these are the baseline's fixed gains; the figures below are "
            f"the searched law's, which failed: {result.reason})" if result.status != "ok" else ""),
        "What the certificate covers: the law and "
        + ("each program's robust baseline (fixed gains below)" if len(result.baselines) == 1
           else "the programs' joint robust baseline (the one fixed setting that keeps every "
           "plant's limits on all of them; its gains below)") + " were replayed from rest",
        f"on {plants if cert.full else len(cert.plants)} plants of the machine's uncertainty "
        "set (the same replay and checks as a table's certificate: paper eq. 2 on every",
        "sample of the velocity command, the following-error limit, Kp inside each plant's "
        "stable range), for these programs at these feed overrides:",
    ]
    for (prog, o), c in cert.cases.items():
        lines.append(f"  {prog} at {o * 100:g} % feed: MSE ratio to the baseline median "
                     f"{c.median:.3f}, p90 {c.p90:.3f}, worst {c.worst:.3f}; plants where the "
                     f"law alone breaks a check: {len(c.breaks('schedule-only'))}")
    b = next(iter(result.baselines.values()))  # several programs: one joint baseline
    lines.append(f"  {'joint ' if len(result.baselines) > 1 else ''}baseline of "
                 f"{', '.join(result.baselines)}: Kp {b.kp:g} (m/min)/mm, Kf {b.kf:g}")
    lines += [
        "Not covered: other programs, feed overrides outside those above, a machine further "
        "from its model than its uncertainty set says,",
        "a law input other than the commanded (setpoint) velocity and acceleration of the "
        "axis, and values changed after export.",
    ]
    return lines
