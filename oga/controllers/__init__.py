"""Comparison controllers from the contouring literature (see :mod:`oga.controllers.base`).

The registry: :data:`CONTROLLERS` names every controller ``oga compare`` knows, in
the order of issue 7; :func:`load_controller` imports one lazily by name, so a
controller module missing from this installation only fails when it is asked for.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable

from oga.errors import OptionError

__all__ = ["CONTROLLERS", "Controller", "load_controller"]

#: Every controller name, in the order of the comparison table.
CONTROLLERS: tuple[str, ...] = (
    "fixed", "oga", "fuzzy-pid", "ccc", "zpetc-ccc-ddob", "smc-dob-ccc", "afsmc",
)


@dataclass(frozen=True)
class Controller:
    """One registered controller.

    Attributes
    ----------
    name : str
        Registry name.
    needs_firmware : bool
        Whether the law needs access to the drive firmware (anything but a gain table).
    parameters : tuple of str
        The parameter names ``run`` accepts.
    run : callable
        ``run(setpoints, machine, *, load_n=None, tune=True, **parameters) -> ControllerRun``.
    """

    name: str
    needs_firmware: bool
    parameters: tuple[str, ...]
    run: Callable


def load_controller(name: str) -> Controller:
    """The controller registered as ``name``.

    Raises
    ------
    OptionError
        Unknown name, or its module is not available (both list the known names).
    """
    if name in ("fixed", "oga"):
        from oga.controllers import gain_table

        if name == "fixed":
            return Controller("fixed", False, gain_table.FIXED_PARAMETERS, gain_table.run_fixed)
        return Controller("oga", False, gain_table.OGA_PARAMETERS, gain_table.run_oga)
    if name not in CONTROLLERS:
        raise OptionError(f"unknown controller {name!r}; known: {', '.join(CONTROLLERS)}")
    module_name = f"oga.controllers.{name.replace('-', '_')}"
    try:
        mod = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name != module_name:
            raise
        raise OptionError(f"controller {name!r} is not available in this installation "
                          f"(no module {module_name}); known: {', '.join(CONTROLLERS)}") from None
    return Controller(mod.NAME, bool(mod.NEEDS_FIRMWARE), tuple(mod.PARAMETERS), mod.run)
