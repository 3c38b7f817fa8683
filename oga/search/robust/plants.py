"""Scenario plants: concrete machines drawn from a machine's uncertainty set.

A machine's cascade axes may carry an :class:`oga.model.machine.Uncertainty`: per parameter a
``(low, high)`` factor range on its nominal value, and extra dead-time samples. This
module turns that set into concrete machines (no uncertainty of their own):

- **Monte Carlo**: each factor drawn independently, per axis, *uniform in its logarithm*
  over ``[low, high]``. The factors scale physical values that are positive and whose
  ranges are stated multiplicatively (x0.5-x2 for force lag and Stribeck velocity), so the
  log scale treats halving and doubling alike and never draws a value near zero; on a
  +-x % range it puts slightly more weight below nominal than above (the median of
  ``(0.5, 1.5)`` is 0.87), which errs towards the low-friction, fast-loop side where the
  identification issue measured the schedules failing. The extra dead time is uniform
  over its whole samples, drawn once per plant over the union of the axes' ranges and
  given to each axis within its own range (:func:`perturbed_machine`): an axis whose
  range is ``(0, 0)`` (e.g. one identified with no doubt about its dead time) never gets
  a sample it was not measured with, whatever another axis's range.
- **Corners**: the groups of :data:`oga.defaults.ROBUST_CORNER_GROUPS` (friction level,
  mass, Kv, Tn, dead time: what moves the result, per the identification issue's
  measurements) each at its low or high end, every uncertain axis at the same end of its
  own range, the other parameters nominal: ``2^g`` corners for the ``g`` groups whose
  range is not a single point (32 for ucp710's default set). All ``2^k`` corners of the
  ``k`` parameters per axis would be ``2^(8 axes + 1)``, mostly of parameters that barely
  matter.

Coulomb and static friction are drawn independently; where a draw puts the static
friction (the Stribeck peak) below the Coulomb level, it is raised to it (a plant with
no Stribeck peak), as the cascade requires ``static_n >= coulomb_n``.

Every plant carries the simulation setting :data:`oga.defaults.ROBUST_FRICTION_LINEAR_BELOW_M_S`
(``timing.friction_linear_below_m_s``, unless the machine sets its own): the hundreds of
replays of a robust search then advance the periods where an axis stands still with one
linear map (the friction taken as its tangent at rest, within the bound of
:class:`oga.model.machine.Timing`) instead of the sub-steps.

Pure functions: the same machine, count and seed give the same plants.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from oga import defaults
from oga.errors import MachineError
from oga.model.machine import FACTOR_FIELDS, Machine, machine_from_dict
from oga.model.plant import PlantBatch

__all__ = [
    "ScenarioSet",
    "uncertain_axes",
    "perturbed_machine",
    "monte_carlo_draws",
    "corner_draws",
    "scenario_set",
]

#: One plant's perturbation: per uncertain axis a factor per FACTOR_FIELDS name, and the
#: extra dead time (samples).
Draw = tuple[dict[str, dict[str, float]], int]


@dataclass(frozen=True, eq=False)
class ScenarioSet:
    """Concrete plants of a machine's uncertainty set.

    Attributes
    ----------
    status : {"ok", "nominal-only"}
        ``"nominal-only"`` when the machine has no uncertainty (the set is its nominal plant).
    nominal : Machine
        The machine the set belongs to.
    plants : tuple of Machine
        The Monte Carlo plants first, then the corners; no uncertainty section of their own
        (:attr:`batch`: the same, packed once into arrays).
    labels : tuple of str
        One per plant: ``"mc-0007"`` or the corner, e.g. ``"corner friction-lo mass-hi ..."``.
    draws : tuple
        One per plant: (per axis {field: factor}, extra dead-time samples).
    seed : int
        Seed of the Monte Carlo draw.
    n_monte_carlo, n_corners : int
        How many plants of each kind.
    """

    status: str
    nominal: Machine
    plants: tuple[Machine, ...]
    labels: tuple[str, ...]
    draws: tuple[Draw, ...]
    seed: int
    n_monte_carlo: int
    n_corners: int

    def __len__(self) -> int:
        return len(self.plants)

    @cached_property
    def batch(self) -> PlantBatch:
        """The plants packed once, stacked with a leading plant axis (:class:`PlantBatch`:
        ``params`` (S, 3, P), ``limits`` (S, 3, 3), ``dead_samples`` (S, 3); ``.machines``
        gives :attr:`plants` back)."""
        return PlantBatch.of(self.plants, self.labels)


def uncertain_axes(machine: Machine) -> tuple[str, ...]:
    """The axes of ``machine`` that carry an uncertainty section, sorted."""
    return tuple(sorted(a for a, ax in machine.axes.items() if ax.uncertainty is not None))


def _dead_range(machine: Machine, axes) -> tuple[int, int]:
    ranges = [machine.axes[a].uncertainty.dead_time_extra_samples for a in axes]
    return min(r[0] for r in ranges), max(r[1] for r in ranges)


def _own_extra(axis, extra: int) -> int:
    """``extra`` samples of dead time within ``axis``'s own range (none for an axis without
    an uncertainty section: it is taken as it is)."""
    if axis.uncertainty is None:
        return 0
    lo, hi = axis.uncertainty.dead_time_extra_samples
    return min(max(extra, lo), hi)


def perturbed_machine(machine: Machine, factors: dict[str, dict[str, float]],
                      dead_extra: int = 0, name: str | None = None,
                      friction_linear_below_m_s: float | None
                      = defaults.ROBUST_FRICTION_LINEAR_BELOW_M_S) -> Machine:
    """``machine`` with its cascade values scaled and its dead time lengthened.

    Parameters
    ----------
    machine : Machine
        The nominal machine.
    factors : dict
        ``{axis: {field: factor}}``, fields of :data:`oga.model.machine.FACTOR_FIELDS`; axes or
        fields left out stay nominal.
    dead_extra : int
        Samples added to each axis's dead time, within the axis's own
        ``dead_time_extra_samples`` range (clipped to it; none on an axis without an
        uncertainty section).
    name : str, optional
        Name of the plant (default ``"<machine>-perturbed"``).
    friction_linear_below_m_s : float or None
        The plant's simulation setting ``timing.friction_linear_below_m_s``
        (:class:`oga.model.machine.Timing`) where ``machine`` sets none (its own value wins), at
        most :data:`oga.defaults.FRICTION_LINEAR_MAX_SHARE` of every cascade axis's
        ``friction_smoothing_m_s`` and ``stribeck_m_s`` (where the friction is linear); None:
        unset (the exact kernel).

    Returns
    -------
    Machine
        Validated; every uncertainty section dropped (it is one concrete plant).

    Raises
    ------
    MachineError
        An unknown axis or field, an ARX axis, or a plant that does not validate.
    """
    data = machine.model_dump(mode="json", exclude_none=True)
    dead = {a: machine.dead_time_samples_of(a) + _own_extra(ax, int(dead_extra))
            for a, ax in machine.axes.items()}
    for ax in data["axes"].values():
        ax.pop("uncertainty", None)
    for a, fs in factors.items():
        cas = data["axes"].get(a, {}).get("cascade")
        if cas is None:
            raise MachineError(f"perturbed plant: axis {a!r} is not a cascade axis of {machine.name!r}")
        for f, x in fs.items():
            if f not in FACTOR_FIELDS:
                raise MachineError(f"perturbed plant: unknown parameter {f!r} of axis {a}")
            cas[f] = cas[f] * float(x)
        cas["static_n"] = max(cas["static_n"], cas["coulomb_n"])
    if len(set(dead.values())) == 1 and float(next(iter(dead.values()))).is_integer():
        data["timing"]["dead_time_samples"] = int(next(iter(dead.values())))  # one for all
        for ax in data["axes"].values():
            ax.pop("dead_time_samples", None)
    else:
        for a, d in dead.items():
            data["axes"][a]["dead_time_samples"] = d
    if friction_linear_below_m_s is not None and "friction_linear_below_m_s" not in data["timing"]:
        data["timing"]["friction_linear_below_m_s"] = min(
            [friction_linear_below_m_s] + [defaults.FRICTION_LINEAR_MAX_SHARE * ax["cascade"][f]
                                           for ax in data["axes"].values() if "cascade" in ax
                                           for f in ("friction_smoothing_m_s", "stribeck_m_s")])
    data["name"] = name or f"{machine.name}-perturbed"
    return machine_from_dict(data, where=f"perturbed plant of {machine.name}")


def monte_carlo_draws(machine: Machine, n: int, seed: int) -> tuple[Draw, ...]:
    """``n`` perturbations drawn log-uniformly from the uncertainty set (module doc).

    Raises
    ------
    MachineError
        ``n`` below 1.
    """
    if n < 1:
        raise MachineError(f"Monte Carlo plants: need at least 1, got {n}")
    rng = np.random.default_rng(seed)
    axes = uncertain_axes(machine)
    dlo, dhi = _dead_range(machine, axes) if axes else (0, 0)
    out = []
    for _ in range(n):
        per_axis = {}
        for a in axes:
            unc = machine.axes[a].uncertainty
            logs = rng.uniform(0.0, 1.0, len(FACTOR_FIELDS))
            per_axis[a] = {
                f: float(np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo))))
                for f, u, (lo, hi) in zip(FACTOR_FIELDS, logs,
                                          (getattr(unc, f) for f in FACTOR_FIELDS))
            }
        out.append((per_axis, int(rng.integers(dlo, dhi + 1))))
    return tuple(out)


def _group_range(machine: Machine, axes, group) -> bool:
    """Whether the group's range is more than one point on some axis."""
    if group == ("dead_time_extra_samples",):
        lo, hi = _dead_range(machine, axes)
        return hi > lo
    return any(getattr(machine.axes[a].uncertainty, f)[0] != getattr(machine.axes[a].uncertainty, f)[1]
               for a in axes for f in group)


def corner_draws(machine: Machine, groups=defaults.ROBUST_CORNER_GROUPS
                 ) -> tuple[tuple[str, ...], tuple[Draw, ...]]:
    """The corners of ``groups`` (module doc): their labels and perturbations.

    Parameters
    ----------
    machine : Machine
    groups : tuple of tuple of str
        Field groups moved together; ``("dead_time_extra_samples",)`` is the dead time.

    Returns
    -------
    labels, draws : tuple
        ``2^g`` each, for the ``g`` groups whose range is not a single point.
    """
    axes = uncertain_axes(machine)
    live = [g for g in groups if axes and _group_range(machine, axes, g)]
    dlo, dhi = _dead_range(machine, axes) if axes else (0, 0)
    labels, draws = [], []
    for ends in itertools.product((0, 1), repeat=len(live)):
        per_axis = {a: {} for a in axes}
        dead = dlo
        for g, end in zip(live, ends):
            if g == ("dead_time_extra_samples",):
                dead = (dlo, dhi)[end]
                continue
            for a in axes:
                for f in g:
                    per_axis[a][f] = float(getattr(machine.axes[a].uncertainty, f)[end])
        names = [("dead" if g[0].startswith("dead") else g[0].split("_")[0] if len(g) == 1
                  else "friction") + ("-lo", "-hi")[e] for g, e in zip(live, ends)]
        labels.append("corner " + " ".join(names))
        draws.append((per_axis, dead))
    return tuple(labels), tuple(draws)


def scenario_set(machine: Machine, n: int = defaults.ROBUST_MC_PLANTS,
                 seed: int = defaults.ROBUST_SEED, corners: bool = True) -> ScenarioSet:
    """The Monte Carlo plants and corners of ``machine``'s uncertainty set.

    Parameters
    ----------
    machine : Machine
        With an uncertainty section on some cascade axes (else the set is the nominal
        plant alone, status ``"nominal-only"``).
    n : int
        Monte Carlo plants.
    seed : int
        Their seed.
    corners : bool
        Add the corners of :func:`corner_draws`.

    Returns
    -------
    ScenarioSet
    """
    if not uncertain_axes(machine):
        return ScenarioSet(status="nominal-only", nominal=machine,
                           plants=(perturbed_machine(machine, {}, 0, machine.name),),
                           labels=("nominal",), draws=(({}, 0),), seed=seed,
                           n_monte_carlo=0, n_corners=0)
    mc = monte_carlo_draws(machine, n, seed)
    labels = [f"mc-{i:04d}" for i in range(n)]
    draws = list(mc)
    n_corners = 0
    if corners:
        c_labels, c_draws = corner_draws(machine)
        labels += c_labels
        draws += c_draws
        n_corners = len(c_draws)
    plants = tuple(perturbed_machine(machine, f, d, f"{machine.name} {lab}")
                   for lab, (f, d) in zip(labels, draws))
    return ScenarioSet(status="ok", nominal=machine, plants=plants, labels=tuple(labels),
                       draws=tuple(draws), seed=seed, n_monte_carlo=n, n_corners=n_corners)
