"""Tolerances, budgets and argument checks shared by the tuner's modules.
"""

from __future__ import annotations

import math

from ..options import PEAK_BOUND_RANGE, check_number, is_number

__all__ = ["STABILITY", "TAIL_RTOL", "MS_RTOL", "CONT_RTOL", "KKT_TOL"]  # the rest is the tuner's own machinery, shared between its modules


#: Classes returned by :meth:`LoopModel.stability`.
STABILITY = ("stable", "marginal", "unstable")

#: Relative bound on the objective's tail beyond the summed samples (IAE, ITAE).
TAIL_RTOL = 1e-6

#: Relative tolerance of the Ms/Mt bound: a result with the bound active has its true peak in
#: ``[bound (1 - MS_RTOL), bound]``.
MS_RTOL = 1e-3

#: Relative accuracy of a continuous loop's reported IAE/ITAE (:meth:`LoopModel.objective_continuous`).
CONT_RTOL = 1e-5

#: First-order optimality tolerance (see ``Tuner._first_order``): the largest relative decrease of
#: the objective per unit relative change of the gains that the active constraints may leave.
KKT_TOL = 2e-3

#: Finite-difference step of that check, in log gain.
FD_STEP = 1e-3

#: Local solves of the true problem after ipopt where the first-order check fails (``Tuner._polish``).
POLISH_ROUNDS = 3

#: That solve's stopping rule: once it has a feasible iterate better than its start, it stops
#: when this many SLSQP iterations in a row have not lowered its best feasible value by
#: ``POLISH_STALL_RTOL`` (relative; the objective's own accuracy is about 1e-10), and returns
#: its best feasible iterate; "feasible" lets a tracked peak or the noise bound exceed its bound
#: (which the polish tightens by 1e-5 relative) by ``POLISH_FEAS_TOL`` relative, half of that
#: tightening (the result is re-verified on the true peaks and bounds all the same).
POLISH_PATIENCE = 3

POLISH_STALL_RTOL = 1e-10

POLISH_FEAS_TOL = 5e-6

#: Largest number of step halvings of that integration (each doubles the samples).
CONT_HALVINGS = 6

#: Eigenvalue modulus tolerance around the unit circle (discrete closed loop).
UNIT_TOL = 1e-9

#: Largest number of samples a loop model may simulate (memory/time budget).
MAX_STEPS = 200_000

#: Largest number of samples summed for an IAE/ITAE tail (budget).
TAIL_MAX_STEPS = 1 << 22

#: Frequencies per loop the NLP can add where the verified peak exceeded the bound. A sharp peak
#: that moves with the gains takes one per round: the ideal PID's IE optimum on 1/(s+1)^3 under
#: Ms <= 1.6 (closed-loop damping ~0.1) needs 13 rounds, and with 12 every ipopt run ran out
#: (tests/tuning/test_generic.py). Unused slots cost nothing measurable.
SLOTS = 24

#: Several loop models (robust tuning): grid rows per loop in the NLP (a coarse subset plus the
#: loop's resonance points; every true peak is still verified on the full grid and beyond), and
#: frequency slots per loop (added in clusters, see ``Tuner._solve_from``).
MULTI_ROWS = 64

MULTI_SLOTS = 40

#: Scan points ranked exactly before the start points are chosen (several loops).
RANK_TOP = 50

#: Restarts from distinct scan points when a solve does not converge.
STARTS = 3

IPOPT_MAX_ITER = 400

#: Decades the peak search may extend below a loop model's grid (where |L| < 100 at its low end).
LOW_DECADES = 8

def checked_number(name: str, value, *, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = True,
            hi_open: bool = True, allow_inf: bool = False, expected: str | None = None) -> float:
    """``value`` as a float, or ValueError naming ``name`` and the expected range
    (:func:`prsa_ctrl.options.check_number` with the tuner's defaults: open bounds; ``allow_inf``:
    +inf accepted too, as "no bound")."""
    exp = expected or (
        f"a finite number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    )
    if allow_inf and is_number(value) and float(value) == math.inf and hi == math.inf:
        return math.inf
    return check_number(name, value, lo, hi, lo_open=lo_open, hi_open=hi_open, expected=exp, typed=repr(value))

def gain_limit(name: str, value) -> float:
    """Upper gain bound: None or inf for none, else a positive number."""
    if value is None:
        return math.inf
    return checked_number(name, value, lo=0.0, allow_inf=True, expected="a positive number, inf or None (no bound)")

def int_steps(name: str, value) -> int:
    return check_number(name, value, 10, MAX_STEPS, integer=True, typed=repr(value),
                        expected=f"an integer in [10, {MAX_STEPS}] (samples)")

def check_mks(mks_max) -> float | None:
    """``mks_max`` as a float, None for no bound, or a ValueError naming it."""
    if mks_max is None:
        return None
    return checked_number("mks_max", mks_max, lo=0.0, expected="a positive finite number or None")

def check_bounds(ms_max, mt_max, max_noise_gain):
    lo, hi = PEAK_BOUND_RANGE
    ms = checked_number("ms_max", ms_max, lo=lo, hi=hi, expected=f"a number in ({lo:g}, {hi:g})")
    mt = None if mt_max is None else checked_number("mt_max", mt_max, lo=lo, hi=hi,
                                              expected=f"a number in ({lo:g}, {hi:g}) or None")
    nz = None if max_noise_gain is None else checked_number(
        "max_noise_gain", max_noise_gain, lo=0.0, expected="a positive finite number or None")
    return ms, mt, nz
