"""Numerical stress: every case returns finite results that close the energy balance, or raises
the clear SimulationError; none returns NaN or hangs (a wall-time budget bounds every run)."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prsa_ctrl import PID, SimulationError, energy_balance, load_plant, simulate
from prsa_ctrl.sim.simulate import SimSettings

PLANT = load_plant()


def _log(lo, hi):
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda v: 10.0**v)


def _check(run, tol):
    """One stress case: either the clear one-line SimulationError of a failed integration, or
    finite results whose energy balance closes to what the tolerance promises.

    The runs here switch the simulator's own energy audit off (``energy_tol = inf``), so the
    balance is checked independently: a dynamics or energy-accounting bug (a wrong sign in a
    dissipated power, a force missing from one body) leaves a residual far above the bound.
    At the loosest tolerance (1e-3) the balance is not promised (it is the case the audit
    exists for), only finiteness.
    """
    try:
        r = run()
    except SimulationError as exc:
        msg = str(exc)
        assert msg.startswith("integration failed between t = ") and "remedy: " in msg and "\n" not in msg, msg
        return "error"
    assert np.all(np.isfinite(r.outputs)) and np.all(np.isfinite(r.states))
    e = energy_balance(r)
    if tol <= 1e-6:
        assert e["relative_residual"] < 1e-4, e
    return "ok"


@settings(max_examples=14, suppress_health_check=[HealthCheck.too_slow])
@given(
    k=_log(1e3, 1e7),
    e=st.floats(1.0, 2.2),
    c=st.one_of(st.just(0.0), _log(1e-2, 500.0)),
    d=_log(1e-4, 1.0),
    kp=st.one_of(st.just(0.0), _log(1e-3, 1e3)),
    ki=st.one_of(st.just(0.0), _log(1e-2, 1e3)),
    final=st.floats(0.0, 10.0),
    tol=st.sampled_from([1e-3, 1e-6, 1e-8, 1e-10]),
)
def test_compliant_contact_grid(k, e, c, d, kp, ki, final, tol):
    plant = PLANT.with_params({
        "contact.stiffness_n_per_mm_e": k, "contact.exponent": e,
        "contact.damping_n_s_per_mm": c, "contact.penetration_mm": d,
    })
    pid = PID(kp, ki) if kp > 0 or ki > 0 else None
    s = SimSettings(rtol=tol, atol=tol, max_wall_s=60.0, energy_tol=math.inf)
    _check(lambda: simulate(plant, load=[(0.0, 500.0), (0.005, final * plant.rated_load_n)], duration=0.02,
                            controller=pid, energy=True, settings=s), tol)


@settings(max_examples=6, suppress_health_check=[HealthCheck.too_slow])
@given(
    kp=_log(1e-3, 1e3),
    ki=st.one_of(st.just(0.0), _log(1e-2, 1e3)),
    final=st.floats(0.0, 10.0),
    horizon=st.floats(0.5, 10.0),
    tol=st.sampled_from([1e-3, 1e-6, 1e-8]),
)
def test_long_horizons_rigid(kp, ki, final, horizon, tol):
    s = SimSettings(rtol=tol, atol=tol, max_wall_s=60.0, energy_tol=math.inf)
    _check(lambda: simulate(PLANT, load=[(0.0, 500.0), (0.1, final * PLANT.rated_load_n)], duration=horizon, dt=1e-3,
                            controller=PID(kp, ki), fidelity="rigid", energy=True, settings=s), tol)


def test_loose_tolerance_that_breaks_the_energy_balance_is_reported():
    plant = PLANT.with_params({"contact.stiffness_n_per_mm_e": 1e3, "contact.exponent": 1.0,
                               "contact.damping_n_s_per_mm": 0.0, "contact.penetration_mm": 1.0})
    s = SimSettings(rtol=1e-3, atol=1e-3)
    with pytest.raises(SimulationError, match=r"untrustworthy integration between t = 0 s and t = 0\.02 s .*energy balance residual.*remedy: tighten rtol/atol \(now 0\.001/0\.001\)"):
        simulate(plant, load=[(0.0, 500.0), (0.005, 0.0)], duration=0.02, energy=True, settings=s)
    # Tighter tolerance: the same case closes.
    r = simulate(plant, load=[(0.0, 500.0), (0.005, 0.0)], duration=0.02, energy=True,
                 settings=SimSettings(rtol=1e-8, atol=1e-8))
    assert energy_balance(r)["relative_residual"] < 1e-6


class _FakeClock:
    """A clock that advances one second each time it is read: the budget is hit after a
    known number of checks, whatever the machine's speed."""

    def __init__(self) -> None:
        self.now = 0.0
        self.reads = 0

    def __call__(self) -> float:
        self.reads += 1
        self.now += 1.0
        return self.now


@pytest.mark.parametrize("discrete", [False, True])
def test_wall_time_budget_raises_instead_of_hanging(discrete):
    """With a 3.5 s budget on a clock that ticks 1 s per read, the run stops at its fourth
    budget check (between integration chunks of at most 0.1 s of simulated time) and says
    where, long before the end of the 1 s run."""
    clock = _FakeClock()
    s = SimSettings(max_wall_s=3.5, clock=clock)
    with pytest.raises(SimulationError, match=r"run stopped at t = 0\.[0-3]\d* s: wall-time budget max_wall_s = 3\.5 s "
                                              r"used up after 4 s \(state \[theta_nut=.*remedy: raise max_wall_s"):
        simulate(PLANT, load=[(0.0, 500.0), (0.01, 1500.0)], duration=1.0, controller=PID(0.085, 14.7), settings=s,
                 fidelity="rigid", discrete=discrete)
    assert clock.reads == 5  # the start, then four checks (the last one fails)


def test_extreme_stiffness_linearises_with_finite_jacobians():
    from prsa_ctrl import linearize

    for k in (1e3, 1e7):
        for e in (1.0, 2.2):
            P = linearize(PLANT.with_params({"contact.stiffness_n_per_mm_e": k, "contact.exponent": e}), 31.4, 1000.0)
            assert np.all(np.isfinite(P.A))
