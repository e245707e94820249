"""The nut's load-dependent loss law of screw-driven axes (ball and roller screws): on which
force it acts (:func:`nut_loss_on_whole_force`) and, in the compliant model, how its magnitude
``|F_s|`` of the force through the nut is smoothed where that force crosses zero
(:func:`smooth_abs`, :func:`nut_loss_band_n`).

Why smoothed: in the compliant model the force through the nut is the helix spring's (spring
plus damper), a state, not a closed form. Under an excitation with accelerations above
``F_load / m`` (a speed multisine on a feed axis) it crosses zero within a sample, twice per
period. With ``|F_s|`` the loss torque ``c |F_s|`` has a kink there: the simulated response is
only piecewise differentiable in the parameters and a Gauss-Newton fit's steps flip across the
kinks (issue 32: 'stalled' after 21 iterations). ``F tanh(F / F_b)`` is smooth, even, zero at
zero and equal to ``|F|`` beyond the band: the difference ``|F| - F tanh(F/F_b) = |F| (1 -
tanh(|F|/F_b))`` is at most ``0.2785 F_b`` (at ``|F| = 0.64 F_b``), below ``1e-6 |F|`` beyond
``7.6 F_b`` and zero in double precision beyond ``20 F_b``.

The band ``F_b`` is :data:`NUT_LOSS_BAND_FRACTION` of the screw's rated load
(``screw.rated_load_n``): the loss torque then differs from the kinked law by at most
``0.2785 * 0.05 = 1.4 %`` of the nut loss at rated load (at 3.2 % of rated load), by less than
1e-4 of itself beyond 25 % of rated load and not at all (double precision) beyond the rated
load,
so the model's static points (load steps, the steady-speed torque under load, the static
deflection) and its linearisation under load are unchanged. The rigid model keeps its closed
form (``_nut_force_rigid`` in :mod:`prsa_ctrl.plant.model`): its force through the nut is an
algebraic function of the state and inputs, and its rigid-law equality tests are unchanged.
"""

from __future__ import annotations

import casadi as ca

from .plantfile import Plant
from .schema import SCREW_DRIVEN

__all__ = ["NUT_LOSS_KEY", "nut_loss_on_whole_force", "NUT_LOSS_BAND_FRACTION", "nut_loss_band_n", "smooth_abs"]

NUT_LOSS_KEY = "axis.nut_loss_on_whole_force"

#: The smoothing band of ``|F_s|`` in the compliant screw-driven model as a fraction of
#: ``screw.rated_load_n`` (module docstring: at most 1.4 % of the rated loss changed). Why 5 %: one collocation step
#: per sample must resolve the transition; on the foreign feed axis's multisine (force through
#: the nut swinging +-10 kN, ~800 N per sample) a 1 % band (40 N) left the Gauss-Newton fit
#: oscillating at a collocation residual of 4e-4..9e-4 (no convergence), 5 % (200 N) converged
#: to 3e-11 in 19 iterations with the fitted values within 0.2 % of the 25 % band's.
NUT_LOSS_BAND_FRACTION = 0.05


def nut_loss_on_whole_force(plant: Plant) -> bool:
    """Whether the rigid model puts the nut's load-dependent loss on the whole force through the
    nut, ``F_s = F_load + m a w'`` (external load plus the carriage's inertial force; ``m`` =
    ``axis.moving_mass_kg``): ``axis.nut_loss_on_whole_force = 1``, the default of ball and
    roller screws. A nut's thread friction grows with the force its flanks carry (Varanasi &
    Nayfeh, J. Dyn. Sys. Meas. Control 126(2) 388-396, 2004, model the thread friction on the
    nut's contact force so); the compliant screw-driven model has this law by construction
    (with the magnitude smoothed, :func:`smooth_abs`) and the rigid one with it is its stiff
    limit. ``0``: the loss on the external load only, the catalogue sizing rule that adds the
    acceleration torque without efficiency (e.g. THK, "Ball Screw: Calculating the Driving
    Torque"); the inverted roller screw (the source paper's rigid model) always has it.
    """
    if plant.mechanism not in SCREW_DRIVEN:
        return False
    flag = plant.values.get(NUT_LOSS_KEY, 1)
    return not (isinstance(flag, (int, float)) and flag == 0)


def nut_loss_band_n(plant: Plant) -> float:
    """The smoothing band ``F_b`` (N) of ``|F_s|``: :data:`NUT_LOSS_BAND_FRACTION` times
    ``screw.rated_load_n`` (a number also when the plant's fitted keys are CasADi symbols: the
    rated load is not a fitted key)."""
    return float(NUT_LOSS_BAND_FRACTION * plant.values["screw.rated_load_n"])


def smooth_abs(x, band: float):
    """``x tanh(x / band)``: ``|x|`` smoothed over ``band`` (same unit as ``x``, > 0); even, 0 at 0,
    at most ``0.2785 band`` below ``|x|`` and equal to it (double precision) beyond ``20 band``.

    Examples
    --------
    >>> round(float(smooth_abs(-5.0, 1.0)), 9), float(smooth_abs(0.0, 1.0)), float(smooth_abs(40.0, 1.0))
    (4.999546021, 0.0, 40.0)
    """
    if not band > 0:
        raise ValueError(f"band = {band!r}; expected a force > 0")
    return x * ca.tanh(x / band)
