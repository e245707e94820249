"""Reference trajectories and state scales of the compliant screw-driven model for the
time-domain fit (:mod:`prsa_ctrl.identification.timedomain`).

The fit's unknowns are deviations from a data-based reference. The rigid states (angle, speed,
torque) come from the log; the compliant model's other states (``x_roller`` the shaft's axial
displacement on its bearing, ``v_roller`` its speed, ``delta_screw`` the helix compression,
``v_screw`` the carriage speed) are not measured. Left at zero they start every segment with
an unloaded spring under a loaded carriage: a transient of the full load at the axial mode that
the first Gauss-Newton steps must remove. Their quasi-static values along the logged motion are
the rigid axis's (the spring carries the load plus the carriage's inertial force):

``F = F_load + m a w'``, ``delta_screw = F / k_H``, ``x_roller = -F / k_B``,
``v_roller = d x_roller / dt``, ``v_screw = a w``

(``a`` the lead per radian, ``m`` = ``axis.moving_mass_kg``, ``k_H``, ``k_B`` the helix and
bearing springs of :func:`prsa_ctrl.plant.model.screw_axis_springs` at the base plant's values;
``w'`` from the logged speed, smoothed over five samples against the encoder noise). Their
scales (the unit one deviation is measured in) are the rated load's deflection of each spring,
the shaft's at the axial mode's rate for its speed, and the speed scale through the lead: without them the collocation equations of a deflection
of 10 um are scaled in metres.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ..plant.model import screw_axis_springs
from .common import inertia_key
from ..plant.plantfile import Plant
from ..plant.schema import AXIAL_MODE_KEYS, axial_mode_keys

__all__ = ["COMPLIANT_STATES", "COMPLIANT_SEGMENT_S", "COMPLIANT_X0_RTOL", "COMPLIANT_G_MAX", "COMPLIANT_F_DROP", "COMPLIANT_RELAXED_STEPS", "SEED_KEYS", "seed_keys", "compliant_start", "unplaced_mode", "placed_by_fit", "shows_mode", "seed_from_frf", "MEASURED_RESPONSE", "LOGS_RESPONSE", "compliant_reference", "compliant_scales"]

#: Singular-value ratio below which a segment's initial-state direction is held at the
#: reference in a Gauss-Newton step of a compliant fit
#: (:func:`prsa_ctrl.identification.gaussnewton.condense`). Measured on the foreign feed axis's
#: multisine (0.1 s segments): the directions of the compliant model's initial state reach the
#: angle with ratios 1, 1.7e-2, 6.9e-3, 4.7e-3, 1.5e-6, 6.7e-7, 3.5e-8 (the rigid model's: 1,
#: 1.1e-2, 8.3e-7); a state-only Newton step keeping all of them is 1e5 state scales long and
#: raises the collocation residual from 0.39 to 13, with 1e-6 to 4.7, with 1e-5 it falls to 0.047
#: (the linearisation holds). The directions held are the fast axial modes' and the torque's,
#: which the segment's data do not determine; the reference keeps them quasi-static.
COMPLIANT_X0_RTOL = 1e-5

#: Line search of a compliant fit: a full Gauss-Newton step is also accepted when it cuts the
#: objective by at least :data:`COMPLIANT_F_DROP` while the largest collocation residual stays
#: within this many state scales, at most :data:`COMPLIANT_RELAXED_STEPS` times per solve (the
#: steps that follow restore the equations: the residual falls quadratically; a converged fit
#: still needs them below 1e-8). Why: the current loop's rate ``(u - tau) / T_c`` is bilinear in
#: the fitted ``1 / T_c`` and the state; at a command step of the full torque range (the
#: staircase's reversals) a full step's residual there is 0.3 scales while the objective falls
#: 15-fold, and the residual-first rule accepted only 1/8 steps: the fit crept (17 iterations,
#: residual 6.9e-3 -> 5.9e-3).
COMPLIANT_G_MAX = 1.0
#: Smallest relative objective decrease of such a step.
COMPLIANT_F_DROP = 0.01
#: Budget of such steps per solve: the restoring steps that follow may raise the objective
#: again, so the two rules can alternate; the budget bounds that (measured on the three foreign
#: logs: with 10 the parameters flipped between two points at a residual of 4e-4 for 20
#: iterations after the 3 relaxed steps the start needed; a filter on the lowest objective
#: instead refused those 3 and the fit crept at 6e-3).
COMPLIANT_RELAXED_STEPS = 4

#: Default multiple-shooting segment of a compliant fit, s (the rigid fit's is 0.1 s). Why
#: shorter: over a segment the angle integrates a collocation defect twice, and the compliant
#: model's fast axial states and the smoothed nut loss make the equations' solution far less
#: linear in the parameters and initial state than the rigid model's. Measured on the foreign
#: feed axis (8 kHz, logs with process torque noise), three-log fit at ``--delay-samples 1``:
#: with 0.1 s segments the fit crept to its iteration budget (52 iterations, 100 s CPU) and the
#: cross-validation refit on multisine + loadsteps stalled from every start ('stalled' at a
#: defect of 2.9e-4, 11 standard errors from a first-order point; the objective at that
#: iterate's restored point, the equations solved with its initial states, was 100x its own);
#: with 0.05 s the fit converged in 19 iterations (41 s CPU; total inertia 4.15665e-3 against
#: 4.15548e-3 kg m^2, truth 4.1563e-3; current loop 1201 against 1218 Hz, truth 1200) and that
#: refit in 11.
COMPLIANT_SEGMENT_S = 0.05

#: The compliant screw-driven model's states that the log does not measure.
COMPLIANT_STATES = ("x_roller", "v_roller", "delta_screw", "v_screw")


def _springs(plant: Plant) -> tuple[float, float]:
    k_h, _, k_b, _, _ = (float(z) for z in screw_axis_springs(plant))
    return k_h, k_b


def _applies(plant: Plant, names: Sequence[str]) -> bool:
    return plant.screw_driven and all(n in names for n in COMPLIANT_STATES)


def compliant_reference(plant: Plant, names: Sequence[str], time_s: NDArray[np.float64], omega_rad_s: NDArray[np.float64],
                        load_n: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Quasi-static values (SI: m, m/s) of the unmeasured compliant states at every sample of a
    log (module docstring); ``{}`` when ``names`` are not the compliant screw-driven model's.

    Parameters
    ----------
    plant : Plant
        Base plant (numeric values).
    names : sequence of str
        The model's state names.
    time_s, omega_rad_s, load_n : array
        The log's time (s), motor speed (rad/s) and external axial load (N).
    """
    if not _applies(plant, names):
        return {}
    k_h, k_b = _springs(plant)
    a = plant.lead_per_rad
    m = float(plant.values["axis.moving_mass_kg"])
    w = np.asarray(omega_rad_s, float)
    if len(w) >= 5:
        w_s = np.convolve(w, np.ones(5) / 5, mode="same")
        w_s[:2], w_s[-2:] = w[:2], w[-2:]
    else:
        w_s = w
    acc = np.gradient(w_s, time_s) if len(w) >= 2 else np.zeros_like(w)
    force = np.asarray(load_n, float) + m * a * acc
    x_r = -force / k_b
    v_r = np.gradient(x_r, time_s) if len(w) >= 2 else np.zeros_like(w)
    return {"x_roller": x_r, "v_roller": v_r, "delta_screw": force / k_h, "v_screw": a * w}


def compliant_scales(plant: Plant, names: Sequence[str], w_scale_rad_s: float) -> dict[str, float]:
    """Scale of each unmeasured compliant state (SI): the rated load's deflection of its spring
    (m) and a tenth of the speed scale through the lead (m/s); ``{}`` for other models."""
    if not _applies(plant, names):
        return {}
    k_h, k_b = _springs(plant)
    f = float(plant.values["screw.rated_load_n"])
    v = 0.1 * w_scale_rad_s * plant.lead_per_rad
    a = plant.lead_per_rad
    j_rot = float(plant.values["axis.motor_inertia_kg_m2"] + plant.values["axis.screw_inertia_kg_m2"])
    w_mode = (k_h * (1.0 / float(plant.values["axis.moving_mass_kg"]) + a * a / j_rot)) ** 0.5  # rad/s
    return {"x_roller": f / k_b, "v_roller": f / k_b * w_mode, "delta_screw": f / k_h, "v_screw": v}


#: Keys of a compliant plant that a two-mass fit of a measured frequency response sets before the
#: time-domain fit (:func:`seed_from_frf`): the axial mode's (the rotating inertia on the motor's
#: side of the spring, the mass on the far side, the spring, its damping), of which the
#: time-domain fit fits the first by default and holds the others unless it frees them; every
#: mechanism's, from the one table :data:`prsa_ctrl.plant.schema.AXIAL_MODE_KEYS` (a screw-driven
#: axis: the rotor, the carriage, the nut and the bearings, the damping; an inverted roller
#: screw: the nut, the translating screw and the thread contacts).
SEED_KEYS = tuple(dict.fromkeys(k for m in AXIAL_MODE_KEYS for k in axial_mode_keys(m)))


def seed_keys(plant: Plant) -> tuple[str, ...]:
    """The axial-mode keys of ``plant``'s mechanism (:func:`prsa_ctrl.plant.schema.axial_mode_keys`;
    ``()`` for a linear axis)."""
    return axial_mode_keys(plant.mechanism)


def compliant_start(plant: Plant, records, frf, keys, command_logged: str, speed_loop=None):
    """The start of a compliant time-domain fit: ``(plant, keys, note)``, the plant seeded from a
    frequency response (:func:`seed_from_frf`), or unchanged with the reason; ``keys`` as given.

    The fit's default keys then take the rotating inertia from the response's start, and the
    mode's spring, far mass and damping keep the response's values: the logs inform them far less
    than the response does (measured on the judge's roller screw logs,
    tests/identification/foreign/gen_judge.py, with ``axis.moving_mass_kg`` and
    ``axis.nut_stiffness_n_per_um`` freed from the response's start: the stiffness's 95 % interval
    +-150 % of its value, its correlations with the inertias 0.95 to 0.997, the fit at the found
    delay stalled from both starts, 126 s of CPU, exit 3), and a written plant keeps the mode
    where the response has it (within 0.1 % there). ``--fit`` frees them all the same.

    The response is ``frf`` (measured, ``--frf``) or, without one, the logs' own
    (:func:`prsa_ctrl.identification.closedloop.frf_from_logs`: joint input-output, the reference
    given back by ``speed_loop``, the drive's described speed loop), used only when it shows a mode
    (:func:`shows_mode`). Without a described loop (and with the default keys) the loop is the one
    identified from a constant-reference log (:func:`prsa_ctrl.identification.closedloop.speed_loop_from_logs`,
    trusted below its residual threshold), and a response through it that places no mode refuses
    the fit (:class:`~prsa_ctrl.errors.FitError`, :func:`unplaced_mode`'s text and why). Without
    any the mode keys stay the base plant's, and the note says why."""
    if not (records and seed_keys(plant)):
        return plant, keys, None
    responses, show_mode, identified = list(frf), False, None
    if not responses and speed_loop is None and keys is None and placed_by_fit(plant):
        return plant, keys, ("the axial-mode keys start from the base plant's, which a measurement placed (their "
                             "sources: fit: ...)")
    if not responses and speed_loop is None and keys is None:
        from .closedloop import speed_loop_from_logs

        speed_loop, identified = speed_loop_from_logs(records, command_logged)
        if speed_loop is None:
            from ..errors import FitError

            raise FitError(_unplaced_text(plant) + f"; {identified}")
    if not responses and speed_loop is not None:
        from ..errors import DataError
        from .closedloop import frf_from_logs

        why = []
        for rec in records:
            try:
                responses.append(frf_from_logs(rec, speed_loop))
            except (DataError, ValueError) as exc:
                why.append(str(exc))
        if not responses:
            why = f"no log gives a frequency response ({'; '.join(why)[:300]})"
            if identified is not None:
                _refuse_identified(plant, identified, why)
            return plant, keys, f"the axial-mode keys stay the base plant's: {why}"
        show_mode = True
    if not responses:
        return plant, keys, ("the axial-mode keys stay the base plant's (not fitted): no measured frequency response "
                             "(--frf FRF.csv) to start them from, and the logs' own needs the drive's speed loop "
                             "described (--speed-loop KP,KI[,TAU_S]: closedloop.frf_from_logs); a compliant fit from a "
                             "misplaced mode does not converge" if keys is None else None)
    start, note = seed_from_frf(plant, responses, command_logged, need_mode=show_mode,
                                origin=LOGS_RESPONSE if show_mode else MEASURED_RESPONSE)
    if identified is not None:
        if start is plant:
            _refuse_identified(plant, identified, note)
        note = f"{identified}; {note} (the joint input-output response through that loop)"
    held = [k for k in seed_keys(start) if k != inertia_key(start) and k not in (keys or ())]
    if start is not plant and held:
        note += f"; {', '.join(held)} keep the response's values (the logs inform them far less)"
    return start, keys, note


def placed_by_fit(plant: Plant) -> bool:
    """Whether a measurement placed the plant's axial mode: its mode keys other than the inertia
    carry a source ``fit: ...`` (as ``prsa-fit --frf`` writes them)."""
    return any(str(plant.sources.get(k, "")).startswith("fit:") for k in seed_keys(plant)[1:])


def unplaced_mode(plant: Plant, records, frf, keys, speed_loop=None, command_logged: str | None = None) -> str | None:
    """Why a compliant time-domain fit is refused before it starts, or ``None``: records, the
    default keys (``keys`` None), and nothing to place the axial mode from: no measured response
    (``frf``) and no described speed loop (``speed_loop``) for the logs' own. The mode keys would
    stay the base plant's (the datasheet's), and a compliant fit from a misplaced mode does not
    converge: measured on the judge's two-mass ball screw
    (tests/identification/foreign/gen_judge.py, its datasheet mode 16 % off) it ran 17 minutes idle
    before it ended exit 3, and 2 min 40 s at the work bound (:mod:`.workbudget`). ``--fit`` keys
    given explicitly fit from the base plant's mode all the same, and a base plant whose mode keys a
    measurement placed (a source ``fit: ...``, as ``prsa-fit --frf`` writes them) starts from them. A log
    run at a constant speed reference gives the loop itself
    (:func:`prsa_ctrl.identification.closedloop.speed_loop_from_logs`, ``command_logged`` as the logs
    have it, None: either): then the start is :func:`compliant_start`'s. :func:`compliant_start`
    refuses the same runs itself, with the logs' convention, before any fit; the fit calls only it,
    so the logs' loop is identified once per run (this answers the question without a start)."""
    if not records or keys is not None or list(frf) or speed_loop is not None or not seed_keys(plant):
        return None
    if placed_by_fit(plant):
        return None
    from .closedloop import speed_loop_from_logs

    why = ""
    for logged in (command_logged,) if command_logged else ("computed", "applied"):
        loop, why = speed_loop_from_logs(records, logged)
        if loop is not None:
            return None
    return _unplaced_text(plant) + f"; {why}"


def _refuse_identified(plant: Plant, identified: str, why: str):
    """The refusal of a compliant fit whose loop, identified from the logs, placed no mode: what
    was identified, why its response placed none (a band suggested for that response is named as
    ``--frf``'s, the only input ``--frf-band`` takes), and the inputs that would."""
    import re

    from ..errors import FitError

    why = why.removeprefix("the compliant fit starts from the base plant's axial mode: ")
    why = re.sub(r": --frf-band ([0-9.eE+-]+,[0-9.eE+-]+)\)$",
                 r" (--frf-band \1 fits a measured response, --frf FRF.csv, in that band; the logs' own cannot be cut))",
                 why)
    raise FitError(f"the compliant fit needs its axial mode placed from a frequency response, and the logs' "
                   f"response placed none; the {identified[0].lower()}{identified[1:]}; why its response placed no "
                   f"mode: {why}; remedy: a measured response (--frf FRF.csv), or the base plant's mode keys "
                   f"({', '.join(seed_keys(plant)[1:])}) fitted from its datasheet's values with --fit KEYS")


def _unplaced_text(plant: Plant) -> str:
    return ("the compliant fit needs its axial mode placed from a frequency response, and none was given: no loop "
            "described: --speed-loop KP,KI[,TAU_S] (the logs' own response through the drive's speed loop) or --frf "
            f"FRF.csv (a measured one); the base plant's mode keys ({', '.join(seed_keys(plant)[1:])}) are its "
            "datasheet's, and a compliant fit from a misplaced mode does not converge (--fit KEYS fits from them all "
            "the same)")


def shows_mode(choice, frf) -> bool:
    """Whether a response shows an axial mode to start a fit from: the structure it chooses is the
    two-mass one (:func:`prsa_ctrl.identification.twomass.choose_structure`), or the two-mass model
    is significantly better and changes the response beyond the noise as that rule asks, with its
    anti-resonance inside the measured band though its mode lies above it. A start needs no
    more: the low band gives the total inertia, the anti-resonance ``sqrt(k / m)`` and the band
    above it the motor side ``J_m`` (the response there is ``1 / (J_m s)``), so the mode
    ``f_a sqrt(J / J_m)`` follows (measured: the judge's roller screw logs, multisine to 150 Hz,
    anti-resonance 137.0 Hz and mode 163.1 Hz against the truth's 137.8 and 161.3 Hz)."""
    from .twomass import STRUCTURE_ALPHA, STRUCTURE_EFFECT

    if choice.structure == "two-mass":
        return True
    if choice.two_mass is None or not (choice.p_value < STRUCTURE_ALPHA and choice.effect > STRUCTURE_EFFECT):
        return False
    lo = min(float(f.frequency_hz[0]) for f in frf)
    hi = max(float(f.frequency_hz[-1]) for f in frf)
    return lo < choice.two_mass.value("antiresonance_hz") < hi


#: What a seeded key's source names as the response its two-mass fit read (:func:`seed_from_frf`):
#: a measured one (``--frf``) or the logs' own, through the drive's speed loop
#: (:func:`prsa_ctrl.identification.closedloop.frf_from_logs`).
MEASURED_RESPONSE = "the measured response"
LOGS_RESPONSE = "the logs' own response"


def seed_from_frf(plant: Plant, frf, command_logged: str, need_mode: bool = False,
                  origin: str = MEASURED_RESPONSE) -> tuple[Plant, str]:
    """``plant`` with :data:`SEED_KEYS` from the two-mass fit of the frequency responses ``frf``
    (:func:`prsa_ctrl.identification.frfplant.fit_frf_structure`, ``fidelity="compliant"``), each
    with the FRF fit's source, and a sentence for the report; ``plant`` unchanged (and the reason)
    when that fit fails or writes none of them, or (``need_mode``) the structure the response
    chooses is the rigid one. ``origin`` (:data:`MEASURED_RESPONSE` or :data:`LOGS_RESPONSE`)
    names the response in each seeded key's source: ``two-mass fit of <origin>, <names> ...``.

    The time-domain fit then starts from the FRF's axial mode instead of the datasheet's (the
    foreign generators' datasheet plants put the mode 24 % and 45 % too high: a time-domain fit
    cannot walk that far through a lightly damped resonance)."""
    import dataclasses

    from ..errors import FitError
    from .frfplant import fit_frf_structure

    names = ", ".join(getattr(f, "name", "FRF") for f in frf)
    try:
        res, choice = fit_frf_structure(frf, plant, fidelity="compliant", command_logged=command_logged)
    except (FitError, ValueError) as exc:
        return plant, f"the compliant fit starts from the base plant's axial mode: the two-mass fit of {names} failed ({exc})"
    if need_mode and not shows_mode(choice, frf):
        return plant, (f"the compliant fit starts from the base plant's axial mode: the response of {names} shows none "
                       f"({choice.reason})")
    keys = [k for k in seed_keys(plant) if k in plant.values and (
        k in res.plant_keys or res.plant.values[k] != plant.values[k])]  # (the bearings: mapped, not refitted)
    if not keys:
        return plant, f"the compliant fit starts from the base plant's axial mode: the two-mass fit of {names} wrote none of {', '.join(seed_keys(plant))}"
    seeded = plant.with_params({k: float(res.plant.values[k]) for k in keys}, name=plant.name)
    sources = dict(seeded.sources)
    for k in keys:
        sources[k] = (f"two-mass fit of {origin}, {names} (start of the time-domain fit): "
                      f"{res.plant.sources.get(k, '')}").rstrip(": ")
    seeded = dataclasses.replace(seeded, sources=sources)
    vals = ", ".join(f"{k} = {seeded.values[k]:.5g}" for k in keys)
    return seeded, f"the compliant fit starts from the two-mass fit of {names}: {vals}"
