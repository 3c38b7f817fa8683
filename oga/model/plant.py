"""The plant: a machine compiled once into what every stage of the pipeline reads.

A :class:`~oga.model.machine.Machine` is the description (pydantic, validated at the edge); a
:class:`Plant` is that description packed for the engine, once: the kernel parameters of
every axis (:func:`oga.model.simulate.axis_params`: sub-step matrices, lifted map, friction), the
kinematic limits, the dead time per axis, the period and the machine's digest; the stable Kp
range per axis (:func:`oga.model.stability.stable_ends`) is read on first use. :func:`plant_of`
keeps one plant per machine digest, so every stage that is handed the same machine (or an
equal one) shares the same arrays.

A :class:`PlantBatch` is a set of plants (a robust scenario set) as arrays with a leading
plant axis: ``params`` (S, 3, P), ``limits`` (S, 3, 3), ``dead_samples`` (S, 3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from feedplan.setpoints import AXES
from oga.model.machine import Machine

__all__ = ["Plant", "PlantBatch", "machine_of", "plant_of"]


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Plant:
    """A machine packed once for the engine.

    Attributes
    ----------
    machine : Machine
        The description it was built from.
    digest : str
        ``machine.digest()``.
    te_s : float
        Position-loop period, s.
    axes : tuple of str
        The machine's axes, in x, y, z order.
    params : ndarray, shape (3, P), read-only
        Packed kernel parameters per axis x, y, z (lifted, :func:`oga.model.simulate.axis_params`);
        a zero row where the machine lacks the axis.
    state_size : int
        Length of an axis state (:func:`oga.model.simulate.state_size`).
    dead_samples : ndarray, shape (3,), read-only
        Dead time per axis, position-loop samples (0 where the machine lacks the axis).
    limits : ndarray, shape (3, 3), read-only
        ``[axis, (vmax m/s, amax m/s^2, jmax m/s^3)]``; 0 where the machine lacks the axis.
    """

    machine: Machine
    digest: str
    te_s: float
    axes: tuple[str, ...]
    params: np.ndarray
    state_size: int
    dead_samples: np.ndarray
    limits: np.ndarray

    @classmethod
    def from_machine(cls, machine: Machine) -> "Plant":
        """Pack ``machine`` (prefer :func:`plant_of`, which keeps one plant per digest)."""
        from oga.model.simulate import _params_of, _sizes  # the packing lives with the kernels

        digest = machine.digest()
        n_params, n_state = _sizes(machine)
        params = np.zeros((3, n_params))
        dead = np.zeros(3)
        for c, a in enumerate(AXES):
            if a in machine.axes:
                params[c] = _params_of(digest, machine, a)
                dead[c] = machine.dead_time_samples_of(a)
        lim = machine.axis_limits()
        limits = np.stack([lim.vmax_m_s, lim.amax_m_s2, lim.jmax_m_s3], axis=1)
        return cls(machine=machine, digest=digest, te_s=float(machine.te),
                   axes=tuple(a for a in AXES if a in machine.axes),
                   params=_frozen(params), state_size=int(n_state),
                   dead_samples=_frozen(dead), limits=_frozen(limits))

    @property
    def name(self) -> str:
        return self.machine.name

    def axis_params(self, axis: str) -> np.ndarray:
        """Packed parameters of ``axis`` (read-only view; MachineError if absent)."""
        self.machine.axis(axis)
        return self.params[AXES.index(axis)]

    def search_params(self) -> np.ndarray:
        """``params`` (3, P), a new array, with an absent axis's row taken from the first
        present axis: the compiled searches advance every row, and an axis the machine lacks
        (its setpoint never moves) must still hold a valid model."""
        first = AXES.index(self.axes[0])
        return np.stack([self.params[c if a in self.axes else first]
                         for c, a in enumerate(AXES)])

    @cached_property
    def stable_kp(self) -> dict[str, tuple[float, float]]:
        """Stable Kp range ``(lo, hi)`` per axis, (m/min)/mm (:func:`oga.model.stability.stable_ends`;
        ``nan`` both where no grid value is stable)."""
        from oga.model.stability import stable_ends

        return {a: stable_ends(self.machine, a) for a in self.axes}


def plant_of(machine: Machine | Plant) -> Plant:
    """The :class:`Plant` of ``machine``, built once per machine digest (a plant: itself)."""
    if isinstance(machine, Plant):
        return machine
    digest = machine.digest()
    plant = _PLANTS.get(digest)
    if plant is None:
        if len(_PLANTS) >= 1024:  # a server sees many machines: keep the memo bounded
            _PLANTS.clear()
        plant = _PLANTS[digest] = Plant.from_machine(machine)
    return plant


def machine_of(machine: Machine | Plant) -> Machine:
    """The machine of a plant, or the machine itself (no packing)."""
    return machine.machine if isinstance(machine, Plant) else machine


#: One plant per machine digest (:func:`plant_of`).
_PLANTS: dict[str, Plant] = {}


@dataclass(frozen=True, eq=False)
class PlantBatch:
    """Plants stacked along a leading axis (a robust scenario set).

    Attributes
    ----------
    plants : tuple of Plant
        One per scenario.
    labels : tuple of str
        One per plant.
    params : ndarray, shape (S, 3, P), read-only
        Packed kernel parameters per plant and axis (zero-padded to the longest P).
    limits : ndarray, shape (S, 3, 3), read-only
    dead_samples : ndarray, shape (S, 3), read-only
    """

    plants: tuple[Plant, ...]
    labels: tuple[str, ...]
    params: np.ndarray
    limits: np.ndarray
    dead_samples: np.ndarray

    @classmethod
    def of(cls, plants, labels=None) -> "PlantBatch":
        """Stack ``plants`` (Plants or Machines, packed once each)."""
        plants = tuple(plant_of(p) for p in plants)
        if labels is None:
            labels = tuple(p.name for p in plants)
        if len(labels) != len(plants):
            raise ValueError(f"labels: {len(labels)} for {len(plants)} plants")
        width = max((p.params.shape[1] for p in plants), default=0)
        params = np.zeros((len(plants), 3, width))
        for s, p in enumerate(plants):
            params[s, :, :p.params.shape[1]] = p.params
        return cls(plants=plants, labels=tuple(labels), params=_frozen(params),
                   limits=_frozen(np.array([p.limits for p in plants]).reshape(-1, 3, 3)),
                   dead_samples=_frozen(np.array([p.dead_samples for p in plants])
                                        .reshape(-1, 3)))

    def __len__(self) -> int:
        return len(self.plants)

    @property
    def machines(self) -> tuple[Machine, ...]:
        """The machines the plants were built from (for callers that still take machines)."""
        return tuple(p.machine for p in self.plants)

    @property
    def te_s(self) -> float:
        """The common period, s (ValueError when the plants differ)."""
        te = {p.te_s for p in self.plants}
        if len(te) != 1 or not all(math.isfinite(t) for t in te):
            raise ValueError(f"plants: periods {sorted(te)} differ")
        return te.pop()
