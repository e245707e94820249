"""What a plant uses, and its description (``prsa-tune --show-plant``).

:func:`keys_read` derives from the model's equations which plant values they use (a run-time
trace and a probe per key, not a list); :func:`used_keys` adds the sampled loop's keys
(:data:`prsa_ctrl.plant.schema.LOOP_KEYS`) and the keys their defaults derive from;
:func:`describe_plant` lists those keys with their values, units and sources. Beside
:mod:`prsa_ctrl.plant.plantfile` (which the model imports) so that the description can read the
model.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path

from ..errors import GeometryWarning
from ..options import FIDELITIES
from ..textsafe import printable
from .model import PlantModel, plant_model
from .plantfile import Plant, load_plant
from .schema import DEFAULTS, KIND, LOOP_KEYS, NON_NEGATIVE_INTEGER, PLAUSIBLE, POSITIVE_INTEGER, UNITS

__all__ = ["keys_read", "used_keys", "describe_plant", "show_plant"]


class _ReadTrace(Mapping):
    """A read-only view of plant values that records every key read by item access or ``get``
    (iteration and ``len`` are not reads)."""

    def __init__(self, values: Mapping) -> None:
        self._values = dict(values)
        self.read: set[str] = set()

    def __getitem__(self, key):
        value = self._values[key]
        self.read.add(key)
        return value

    def __iter__(self):
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)


def _view(plant: Plant, values: Mapping) -> Plant:
    """``plant`` with ``values`` in place of its own (no validation: a trace or a probe)."""
    import dataclasses

    view = object.__new__(Plant)
    for f in dataclasses.fields(Plant):
        object.__setattr__(view, f.name, getattr(plant, f.name))
    object.__setattr__(view, "values", values)
    return view


def _probe_value(key: str, value: float) -> float:
    """A changed value of ``key`` (file units): one less for an integer that stays in its kind's
    range (0/1 switches such as ``axis.nut_loss_on_whole_force`` read any non-zero value as 1,
    so one more would change nothing), else one more; 25 % more for a number, a thousandth of
    its plausible maximum for a zero."""
    kind = KIND.get(key)
    if kind in (POSITIVE_INTEGER, NON_NEGATIVE_INTEGER):
        return value - 1 if value - 1 >= (1 if kind == POSITIVE_INTEGER else 0) else value + 1
    return 1.25 * value if value != 0 else 1e-3 * PLAUSIBLE.get(key, (0.0, 1.0, ""))[1]


def _differs(a: PlantModel, b: PlantModel) -> bool:
    """Whether ``a`` and ``b`` differ beyond rounding (1e-9 relative) in f, h or power at seeded
    states whose motor speed sweeps 0 and +-1e-7 ... 1e2 rad/s in quarter decades (the stick
    band and its blend, the Stribeck range and running speed), both load directions; a
    non-finite value counts as a difference."""
    import numpy as np

    mag = {"x_roller": 3e-5, "delta_screw": 3e-5, "v_roller": 2e-3, "v_screw": 2e-3, "omega_cage": 20.0, "tau_motor": 1.0}
    rng = np.random.default_rng(12345)
    speeds = [0.0] + [s * 10.0 ** (k / 4.0) for k in range(-28, 9) for s in (1.0, -1.0)]
    for w in speeds:
        x = [w if k == "omega_nut" else mag.get(k, 1.0) * rng.uniform(-1.0, 1.0) for k in a.state_names]
        u = [rng.uniform(-2.0, 2.0), rng.uniform(-3000.0, 3000.0)]
        for fa, fb in ((a.f, b.f), (a.h, b.h), (a.power, b.power)):
            va, vb = np.asarray(fa(x, u), float), np.asarray(fb(x, u), float)
            if not (np.all(np.isfinite(va)) and np.all(np.isfinite(vb))):
                return True
            if np.any(np.abs(va - vb) > 1e-9 * np.maximum(np.abs(vb), 1e-12 * max(1.0, float(np.max(np.abs(vb)))))):
                return True
    return False


def keys_read(plant: Plant) -> frozenset:
    """The plant values (keys ``section.key``) the model of ``plant`` uses: derived from the
    equations of every fidelity of its mechanism (``rigid``, ``compliant`` and, for the inverted
    roller screw, ``multi-roller``), not from a list.

    A run-time trace records the keys the equations' construction reads
    (:func:`~prsa_ctrl.plant.model.plant_model` of a recording view of the values); a key the
    rigid and compliant equations read is kept where changing it (:func:`_probe_value`) changes
    their ``f``, ``h`` or ``power`` beyond rounding (1e-9
    relative) at seeded states over the whole speed range (:func:`_differs`), so a value that is
    read and cancels out (the thread's flank angle in the loss torque of a screw-driven axis,
    which the efficiency sets) is not counted; a key only the multi-roller equations read is
    kept. The sampled loop's keys (drive and sensor, :data:`prsa_ctrl.plant.schema.LOOP_KEYS`) are read by the controller and the
    simulator, not by these equations.

    Examples
    --------
    >>> from prsa_ctrl import load_plant
    >>> "roller.count" in keys_read(load_plant("ballscrew-32x10"))
    False
    """
    fidelities = [f for f in FIDELITIES if f != "multi-roller" or plant.mechanism == "inverted-roller-screw"]
    read: dict[str, set] = {}
    for fidelity in fidelities:
        trace = _ReadTrace(plant.values)
        plant_model(_view(plant, trace), fidelity)
        read[fidelity] = trace.read
    core = [f for f in fidelities if f != "multi-roller"]
    refs = {f: plant_model(plant, f) for f in core}
    used = set(read.get("multi-roller", set())) - set().union(*(read[f] for f in core))
    for key in sorted(set().union(*(read[f] for f in core))):  # bounded: one probe per key read
        values = dict(plant.values)
        values[key] = _probe_value(key, float(plant.values[key]))
        probe = _view(plant, values)  # as a file giving the changed value (a defaulted key then counts)
        object.__setattr__(probe, "defaulted", frozenset(plant.defaulted) - {key})
        try:
            changed = any(_differs(plant_model(probe, f), refs[f]) for f in core if key in read[f])
        except (RuntimeError, ValueError, TypeError, ArithmeticError):
            changed = True  # the equations cannot take the changed value: they depend on it
        if changed or key in read.get("multi-roller", set()):
            used.add(key)
    return frozenset(used)


class _Inputs(dict):
    """Records the keys a default rule reads."""

    def __init__(self, values: Mapping[str, float]) -> None:
        super().__init__(values)
        self.read: set[str] = set()

    def __getitem__(self, key):
        self.read.add(key)
        return super().__getitem__(key)


def used_keys(plant: Plant) -> tuple[str, ...]:
    """The keys ``plant`` uses, in the order of ``plant.values``: the keys its model's equations
    use (every fidelity of its mechanism, traced: :func:`keys_read`), the sampled loop's keys
    (:data:`~prsa_ctrl.plant.schema.LOOP_KEYS`) and, for each of those the file left out, the keys
    its default rule reads (:data:`~prsa_ctrl.plant.schema.DEFAULTS`), transitively. Every other
    key changes nothing for this plant (a ball screw's roller, cage and contact keys).

    Examples
    --------
    >>> keys = used_keys(load_plant("ballscrew-32x10"))
    >>> "axis.moving_mass_kg" in keys, "roller.count" in keys
    (True, False)
    """
    used = set(keys_read(plant)) | {k for k in LOOP_KEYS if k in plant.values}
    todo = list(used)
    while todo:  # bounded: each key enters at most once
        key = todo.pop()
        rule = DEFAULTS[key][0] if key in plant.defaulted and key in DEFAULTS else None
        if not callable(rule):
            continue
        inputs = _Inputs(plant.values)
        rule(inputs, plant.mechanism)
        for k in inputs.read - used:
            used.add(k)
            todo.append(k)
    return tuple(k for k in plant.values if k in used)


def describe_plant(plant: Plant) -> str:
    """Every value ``plant`` uses (:func:`used_keys`) with its unit and its source, one line each,
    grouped by section; the keys its mechanism does not use are left out (a ball screw has no
    rollers, cage or thread contacts to describe), and a key the file gives that the plant does
    not use is named in a last ``given but not used`` line.

    Each line says ``given`` (the plant file's value, with the file's source string) or
    ``default`` / ``derived`` (the key was left out: the value of
    :data:`~prsa_ctrl.plant.schema.DEFAULTS` and the reason). The header names the plant,
    its file, the mechanism (with its source), the coordinates the plant works in (a linear axis:
    load, m and N; every other mechanism: motor, rad and N m) and what the plant's compliant
    fidelity is.

    Examples
    --------
    >>> print(describe_plant(load_plant()).splitlines()[1])
    mechanism: inverted-roller-screw (default: inverted-roller-screw)
    """
    lines = [f"plant {printable(plant.name)} ({printable(plant.origin)})"
             f"{': ' + printable(plant.description) if plant.description else ''}",
             f"mechanism: {plant.mechanism} ({plant.mechanism_source})",
             "coordinates: " + ("load (position m, force N)" if plant.mechanism == "linear-axis"
                                else "motor (angle rad, torque N m)")]
    if plant.screw_driven:
        v = plant.values
        lines.append(f"axial stiffness at the stroke position {v['axis.stroke_position_mm']:g} mm: "
                     f"{plant.axial_stiffness_n_per_m() * 1e-6:.4g} N/um, axial mode {plant.axial_mode_hz():.4g} Hz "
                     f"({'fixed-fixed' if v['axis.fixed_ends'] == 2 else 'fixed-free'}; the series formula "
                     "sqrt(k (1/m + a^2/J)) / 2 pi at no load and without the nut loss: the mode at an operating "
                     "point, which moves with the nut force, is prsa-fit's 'axial mode of the written plant')")
    used = used_keys(plant)
    order = list(dict.fromkeys(k.split(".")[0] for k in used))  # each section once (a screw axis adds screw keys)
    used = tuple(sorted(used, key=lambda k: order.index(k.split(".")[0])))  # stable: file order inside a section
    width = max(len(k) for k in used)
    section = None
    for key in used:
        value = plant.values[key]
        sec = key.split(".")[0]
        if sec != section:
            lines.append(f"[{sec}]")
            section = sec
        src = plant.sources.get(key, "")
        tag = "given" if key not in plant.defaulted else ("derived" if src.startswith("derived") else "default")
        unit = UNITS.get(key, "-")
        shown = str(int(value)) if KIND.get(key) in (POSITIVE_INTEGER, NON_NEGATIVE_INTEGER) else f"{value:.6g}"
        lines.append(f"  {key:<{width}} = {shown:>12} {unit:<10} {tag:<7} {printable(src)}")
    idle = [k for k in plant.values if k not in used and k not in plant.defaulted]
    if idle:
        lines.append(f"given but not used by the {plant.mechanism} model: {', '.join(idle)}")
    return "\n".join(lines)


def show_plant(name_or_path: str | Path | None = None) -> str:
    """:func:`describe_plant` of a plant file (``prsa-tune --show-plant``); the geometry notes
    of the inverted design are lines of the text instead of warnings."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        plant = load_plant(name_or_path)
    return describe_plant(plant) + "".join(f"\ngeometry note: {m}" for m in plant.geometry.messages)


