"""A certified law in each controller's own terms.

- :mod:`oga.law.export.linuxcnc`: HAL (``abs`` + ``lincurve`` on the commanded velocity).
- :mod:`oga.law.export.twincat`: TwinCAT CNC axis parameters (dynamic Kv).
- :mod:`oga.law.export.heidenhain`: Heidenhain MAC support points (TNCopt).

:func:`law_files` picks them by the law's kind; every file opens with a comment block
saying what the certificate covers (:mod:`oga.law.export.common`).
"""

from __future__ import annotations

__all__ = ["law_files"]


def law_files(result, machine_name: str, plants: int, *, units: str = "mm",
              joints: dict[str, int] | None = None) -> dict[str, str]:
    """File name -> text of ``result``'s law for its controller: ``lincurve``, ``lincurve-sa``: LinuxCNC
    HAL; ``pl``: TwinCAT CNC (two points) and LinuxCNC HAL; ``mac``: Heidenhain MAC."""
    from oga.law.export.heidenhain import HEIDENHAIN, heidenhain_text
    from oga.law.export.linuxcnc import LAW_HAL, law_hal
    from oga.law.export.twincat import twincat_files

    from oga.law.export.common import certificate_lines

    law, comment = result.law, certificate_lines(result, machine_name, plants)
    if law.kind == "mac":
        return {HEIDENHAIN: heidenhain_text(law, comment)}
    out = {LAW_HAL: law_hal(law, comment, units=units, joints=joints)}
    if law.kind == "pl" and all(len(ax.v_m_s) == 2 for ax in law.axes.values()):
        out.update(twincat_files(law, comment))
    return out
