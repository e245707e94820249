"""The adaptive RODAS4 integrator of the continuous loop (SimSettings(integrator="rodas")): its
tableau's order conditions, its error on a stiff linear system against the exact solution, on the
paper load step against a tight CVODES run (error controlled by the tolerance), its step budget,
and its refusal of the sampled loop."""

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import expm

from prsa_ctrl import PID, load_plant
from prsa_ctrl.errors import SimulationError
from prsa_ctrl.sim.engine import run
from prsa_ctrl.sim.integrators import SimSettings, build, continuous_integrator, lu_kernels
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.sim.rosenbrock import CHUNK_ATTEMPTS, RODAS4, RodasSegment, rodas_attempt

PLANT = load_plant()
W300 = 31.41592653589793
#: The paper load step, continuous controller (the work-precision benchmark's problem, shorter).
STEP = dict(setpoint=W300, load=[(0.0, 500.0), (0.002, 1500.0)], duration=0.02, controller=PID(0.0849, 14.67),
            dt=1e-4)


def _full(values, n=6):
    m = np.zeros((n, n))
    m[np.tril_indices(n, -1)] = values
    return m


def test_the_tableau_is_stiffly_accurate():
    # The last two stages sit at the step's end, stage 6 starts from stage 5's result and the
    # solution is stage 6's: the error estimate is the last stage alone.
    alpha = np.asarray(RODAS4["alpha"])
    assert alpha[-1] == alpha[-2] == 1.0
    a = _full(RODAS4["a"])
    # Stiffly accurate: stage 6's input equals stage 5's output and the solution is stage 6's output.
    assert np.allclose(a[5, :5], RODAS4["m"][:5])
    assert np.allclose(a[4, :4], RODAS4["m"][:4])
    assert RODAS4["e"] == (0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def _linear_segment(a_mat, n_out, tol, max_attempts=10**6):
    nz = a_mat.shape[0]
    z, p, t = ca.SX.sym("z", nz), ca.SX.sym("p", 1), ca.SX.sym("t")
    f = ca.Function("f", [z, p, t], [ca.DM(a_mat) @ z + p[0] * t])
    chunk = rodas_attempt(f, nz, 1, lu_kernels).mapaccum("c", CHUNK_ATTEMPTS, [0], [0])
    return RodasSegment(chunk, nz, n_out, tol, tol, max_attempts)


def test_a_stiff_oscillator_matches_the_exact_solution_within_the_tolerance():
    # A lightly damped mode near the imaginary axis (damping 0.03) and a stiff real one: the
    # eigenvalues on which BDF orders 3-5 are not stable, in normalised time over one segment.
    w, zeta, fast = 40.0, 0.03, -1e6
    a_mat = np.array([[0.0, 1.0, 0.0], [-w * w, -2 * zeta * w, 0.0], [0.0, 0.0, fast]])
    z0 = np.array([1.0, 0.0, 1.0])
    n_out = 50
    exact = np.column_stack([expm(a_mat * (k / n_out)) @ z0 for k in range(1, n_out + 1)])
    errs = []
    for tol in (1e-6, 1e-8):
        seg = _linear_segment(a_mat, n_out, tol)
        xs = seg(x0=z0, p=[0.0])["xf"]
        assert xs.shape == (3, n_out)
        assert np.all(np.isfinite(xs))
        errs.append(float(np.max(np.abs(xs - exact))))
        assert seg.stats["accepted"] >= n_out
    # Measured 8.7e-5 and 9.1e-7 (global error over 3 periods of the oscillator).
    assert errs[0] < 3e-4
    assert errs[1] < 3e-6
    assert errs[1] < errs[0] / 30  # the error follows the tolerance


def test_a_forced_system_takes_the_time_derivative_into_account():
    # dz/dt = -z + t, z(0) = 0: z = t - 1 + exp(-t).
    seg = _linear_segment(np.array([[-1.0]]), 10, 1e-9)
    xs = seg(x0=[0.0], p=[1.0])["xf"][0]
    t = np.arange(1, 11) / 10
    assert np.max(np.abs(xs - (t - 1 + np.exp(-t)))) < 1e-9  # measured 6.6e-11


@pytest.fixture(scope="module")
def reference():
    return run(PLANT, fidelity="compliant", settings=SimSettings(rtol=1e-12, atol=1e-12), **STEP)


@pytest.mark.parametrize("tol", [1e-6, 1e-8])
def test_the_paper_load_step_matches_a_tight_cvodes_run(reference, tol):
    r = run(PLANT, fidelity="compliant", settings=SimSettings(integrator="rodas", rtol=tol, atol=tol), **STEP)
    assert np.array_equal(r.time, reference.time)
    w, w_ref = r.output("nut_speed"), reference.output("nut_speed")
    drop = W300 - w_ref.min()
    assert drop > 2.0
    err = float(np.max(np.abs(w - w_ref)))
    # The nut speed is scaled by 100 rad/s, so tol bounds its local error at 100 tol rad/s; the
    # global error measured here: 1.37e-6 rad/s (tol 1e-6) and 1.5e-8 rad/s (tol 1e-8).
    assert err < 5 * tol
    assert np.allclose(r.states[:, -1], reference.states[:, -1], rtol=1e-4, atol=1e-6)


def test_tighter_tolerances_take_more_steps_and_land_on_every_output():
    model = plant_model(PLANT, "compliant")
    built = build(model, False)
    steps = []
    for tol in (1e-5, 1e-8):
        s = SimSettings(integrator="rodas", rtol=tol, atol=tol)
        run(PLANT, fidelity="compliant", settings=s, **STEP)
        seg = continuous_integrator(built, s, 180)
        assert isinstance(seg, RodasSegment)
        assert seg.n_out == 180
        steps.append(seg.stats["accepted"])
    assert 180 <= steps[0] < steps[1]


def test_the_step_budget_is_enforced():
    with pytest.raises(SimulationError, match="step attempts"):
        run(PLANT, fidelity="compliant", settings=SimSettings(integrator="rodas", rtol=1e-10, atol=1e-10,
                                                                max_steps=10), **STEP)


def test_the_sampled_loop_refuses_rodas():
    with pytest.raises(ValueError, match="'rodas' with discrete = True"):
        run(PLANT, fidelity="rigid", discrete=True, settings=SimSettings(integrator="rodas"),
            setpoint=W300, load=500.0, duration=0.01, controller=PID(0.0849, 14.67))


def test_jit_runs_the_same_steps_as_compiled_code_from_the_per_user_cache(tmp_path, monkeypatch):
    import prsa_ctrl.sim.integrators as S

    monkeypatch.setenv("PRSA_CTRL_CACHE", str(tmp_path))
    monkeypatch.setattr(S, "_COMPILED", {})
    kw = dict(STEP, duration=0.01, fidelity="rigid")
    plain = run(PLANT, settings=SimSettings(integrator="rodas", rtol=1e-8, atol=1e-8), **kw)
    jit = run(PLANT, settings=SimSettings(integrator="rodas", rtol=1e-8, atol=1e-8, jit=True), **kw)
    assert len(list((tmp_path / "jit").glob("rodas_chunk_*.so"))) == 1
    # the same equations and step control; compiled arithmetic may round differently
    np.testing.assert_allclose(jit.outputs, plain.outputs, rtol=1e-9, atol=1e-9)


def test_ramped_setpoint_and_load_match_a_tight_cvodes_run():
    # The ramps' slopes make the right-hand side depend on time (the step's dF/dt term).
    from prsa_ctrl.sim.signals import PiecewiseLinear

    kw = dict(setpoint=PiecewiseLinear([(0, W300), (0.01, W300), (0.03, 20.0)]),
              load=PiecewiseLinear([(0, 500.0), (0.005, 500.0), (0.02, 1500.0)]), duration=0.04,
              controller=PID(0.0849, 14.67), dt=1e-4, fidelity="compliant")
    ref = run(PLANT, settings=SimSettings(rtol=1e-12, atol=1e-12), **kw).output("nut_speed")
    w = run(PLANT, settings=SimSettings(integrator="rodas", rtol=1e-8, atol=1e-8), **kw).output("nut_speed")
    assert np.max(np.abs(w - ref)) < 1e-7  # measured 2.0e-8


def test_a_solution_that_blows_up_ends_in_one_runtime_error_not_nan():
    # dz/dtau = 10 z^2, z(0) = 1 reaches infinity at tau = 0.1: the steps shrink below 1e-13 of
    # the segment or the state stops being finite, and the segment says so.
    z, p, t = ca.SX.sym("z", 1), ca.SX.sym("p", 1), ca.SX.sym("t")
    f = ca.Function("f", [z, p, t], [10.0 * z ** 2])
    chunk = rodas_attempt(f, 1, 1, lu_kernels).mapaccum("c", CHUNK_ATTEMPTS, [0], [0])
    seg = RodasSegment(chunk, 1, 10, 1e-8, 1e-8, 10**5)
    with pytest.raises(RuntimeError, match="RODAS4: step size .* at 0.1 of it"):
        seg(x0=[1.0], p=[0.0])


def test_the_wall_time_budget_stops_a_rodas_segment_inside_it():
    # One long segment (2 ms to 20 ms after the load step) of ~40 chunks at tol 1e-8: the budget is
    # checked between the chunks, so a fake clock that ticks 1 s per reading stops the run inside
    # the segment at the first reading past max_wall_s, with the budget's own message.
    ticks = []

    def clock():
        ticks.append(len(ticks))
        return float(ticks[-1])

    s = SimSettings(integrator="rodas", rtol=1e-8, atol=1e-8, max_wall_s=4.5, clock=clock)
    with pytest.raises(SimulationError, match=r"^run stopped at t = (\S+) s: wall-time budget") as err:
        run(PLANT, fidelity="compliant", settings=s, **STEP)
    t_stop = float(err.value.args[0].split("t = ")[1].split(" s")[0])
    assert 0.002 < t_stop < 0.02
    assert len(ticks) == 6  # the start, then 5 checks: stopped at the first over 4.5 s


def _one_step(f, nz, npar):
    """One RODAS4 step of size h from (t0, z0), accepted whatever its error (tolerances 1e10)."""
    att = rodas_attempt(f, nz, npar, lu_kernels)

    def step(t0, h, z0, p):
        st1 = np.asarray(att(np.r_[t0, h, z0], p, [1.0, 1e10, 1e10])[0]).ravel()
        assert st1[0] == pytest.approx(t0 + h, abs=1e-15)  # one step of exactly h
        return st1[2:]
    return step


def test_one_step_has_local_error_of_order_five_on_a_nonlinear_time_dependent_system():
    # The implemented step (tableau, stage times, dF/dt terms, LU solves), not the tableau alone: on
    # a nonlinear system with explicit time dependence the local error of an order-4 method falls
    # as h^5 against an independent DOP853 run at 1e-13. Scratch check: changing any one of the 53
    # coefficients by 1 % drops the measured slope to 4.5 or below (1-2 for most).
    from scipy.integrate import solve_ivp

    z, p, t = ca.SX.sym("z", 3), ca.SX.sym("p", 1), ca.SX.sym("t")
    rhs = ca.vertcat(z[1], -z[0] + 0.5 * (1 - z[0] ** 2) * z[1] + ca.cos(3 * t), -z[2] * z[0] + t ** 2)
    f = ca.Function("f", [z, p, t], [rhs])
    step = _one_step(f, 3, 1)
    z0, t0 = np.array([0.8, -0.3, 1.2]), 0.2
    errs = []
    for h in (0.05, 0.025, 0.0125):
        ref = solve_ivp(lambda tt, y: np.asarray(f(y, 0.0, tt)).ravel(), (t0, t0 + h), z0, method="DOP853",
                        rtol=1e-13, atol=1e-13).y[:, -1]
        errs.append(float(np.max(np.abs(step(t0, h, z0, [0.0]) - ref))))
    slopes = np.log2(np.array(errs[:-1]) / errs[1:])
    assert np.all(slopes > 4.7), (errs, slopes)  # measured 4.85, 4.94 (order 3 would give ~4)


def test_the_step_is_a_stable_and_stiffly_damped_on_the_left_half_plane():
    # The stability function R(h lambda) of one step on z' = [[x, y], [-y, x]] z (eigenvalues
    # x +/- iy): |R| <= 1 on the imaginary axis and the left half-plane (A-stable), and |R| -> 0
    # as |h lambda| -> inf (L-stable: no ringing of the stiff modes the compliant plants have).
    z, p, t = ca.SX.sym("z", 2), ca.SX.sym("p", 2), ca.SX.sym("t")
    f = ca.Function("f", [z, p, t], [ca.vertcat(p[0] * z[0] + p[1] * z[1], -p[1] * z[0] + p[0] * z[1])])
    step = _one_step(f, 2, 2)

    def r(x, y):
        return float(np.hypot(*step(0.0, 0.5, [1.0, 0.0], [2 * x, 2 * y])))  # h = 0.5: h lambda = x + iy

    assert r(-1.0, 0.0) == pytest.approx(np.exp(-1.0), abs=1e-3)  # order 4 near the origin
    for y in np.logspace(-2, 8, 21):
        assert r(0.0, y) <= 1.0 + 1e-12
        for x in (-1e-3, -1.0, -1e2, -1e5):
            assert r(x * max(y, 1.0), y) <= 1.0 + 1e-12
    assert r(-1e8, 0.0) < 1e-6
    assert r(0.0, 1e8) < 1e-6  # measured 8.8e-8 both


#: Plants and inputs the paper load step does not exercise: other screws (stiffness, lead, limits),
#: the multi-roller model (more states: another LU sparsity), a setpoint with kinks (restarts with
#: slopes) and a torque-saturating run (the clip makes the right-hand side non-smooth).
CASES = {
    "ballscrew": ("ballscrew-32x10", dict(STEP, fidelity="compliant")),
    "rollerscrew": ("rollerscrew-30x5", dict(STEP, fidelity="compliant")),
    "multi-roller": ("paper-iprsm", dict(STEP, duration=0.01, fidelity="multi-roller")),
    "kinks": ("paper-iprsm", dict(STEP, load=500.0, duration=0.03, fidelity="compliant", setpoint=[
        (0.0, 0.0), (0.004, 0.0), (0.012, W300), (0.02, W300), (0.024, -W300)])),
    "saturating": ("paper-iprsm", dict(STEP, duration=0.02, load=[(0.0, 500.0), (0.01, 8000.0)], setpoint=[
        (0.0, 0.0), (0.002, 3 * W300)], fidelity="compliant")),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_other_plants_and_inputs_match_a_tight_cvodes_run_within_the_tolerance(case):
    from prsa_ctrl.sim.integrators import state_scale
    from prsa_ctrl.sim.signals import PiecewiseLinear

    name, kw = CASES[case]
    kw = dict(kw)
    if isinstance(kw["setpoint"], list):
        kw["setpoint"] = PiecewiseLinear(kw["setpoint"])
    plant = load_plant(name)
    ref = run(plant, settings=SimSettings(rtol=1e-12, atol=1e-12, max_steps=10**6), **kw)
    r = run(plant, settings=SimSettings(integrator="rodas", rtol=1e-8, atol=1e-8), **kw)
    assert np.array_equal(r.time, ref.time)
    assert np.all(np.isfinite(r.states))
    scale = np.r_[state_scale(plant_model(plant, kw["fidelity"])), 100.0, plant.torque_limit, 100.0]
    assert scale.size == r.states.shape[0]
    if case == "saturating":  # the run does saturate
        assert np.mean(np.abs(ref.output("torque_command")) >= plant.torque_limit * (1 - 1e-9)) > 0.3
    err = float(np.max(np.abs(r.states - ref.states) / scale[:, None]))
    # Global error on the scaled states (what rtol/atol bound locally): measured 6-72 x tol at 1e-8
    # on these (CVODES at the same tolerance: 66-731 x); the reference's own error is <= 5e-9.
    assert err < 100 * 1e-8, err


def test_the_error_estimate_sets_steps_that_follow_the_tolerance_on_a_smooth_system():
    # The step control rests on the embedded estimate: with the right one (order 3, the last stage)
    # the steps grow as tol^(-1/4) and the global error stays below the tolerance. Measured here:
    # 32 and 211 steps at 1e-6 and 1e-10 (ratio 6.6), errors 0.023-0.057 x tol. An estimate from
    # stage 5 instead takes 53 and 919 steps (ratio 17); one 10 x too optimistic errs 0.2-0.5 x tol.
    from scipy.integrate import solve_ivp

    z, p, t = ca.SX.sym("z", 3), ca.SX.sym("p", 1), ca.SX.sym("t")
    rhs = ca.vertcat(z[1], -z[0] + 0.5 * (1 - z[0] ** 2) * z[1] + ca.cos(3 * t), -z[2] * z[0] + t ** 2)
    f = ca.Function("f", [z, p, t], [rhs])
    z0 = np.array([0.8, -0.3, 1.2])
    ref = solve_ivp(lambda tt, y: np.asarray(f(y, 0.0, tt)).ravel(), (0.0, 1.0), z0, method="DOP853", rtol=1e-13,
                    atol=1e-13, t_eval=np.arange(1, 11) / 10).y
    chunk = rodas_attempt(f, 3, 1, lu_kernels).mapaccum("c", CHUNK_ATTEMPTS, [0], [0])
    steps = {}
    for tol in (1e-6, 1e-8, 1e-10):
        seg = RodasSegment(chunk, 3, 10, tol, tol, 10**5)
        err = float(np.max(np.abs(seg(x0=z0, p=[0.0])["xf"] - ref)))
        steps[tol] = seg.stats["accepted"]
        assert err < 0.1 * tol, (tol, err)
    assert 10 <= steps[1e-6] < steps[1e-8] < steps[1e-10] < 10 * steps[1e-6], steps


def test_a_tolerance_below_double_precision_ends_in_one_error_naming_it():
    # rtol = atol = 1e-300 is accepted by SimSettings (a tolerance in (0, 1)) but no step meets it:
    # the steps shrink below 1e-13 of the segment within the first chunks and the error names the
    # tolerances (CVODES says "CV_TOO_MUCH_ACC").
    s = SimSettings(integrator="rodas", rtol=1e-300, atol=1e-300)
    with pytest.raises(SimulationError, match=r"RODAS4: step size .* rtol = 1e-300, atol = 1e-300 below what double"):
        run(PLANT, fidelity="compliant", settings=s, **STEP)


def test_a_loose_tolerance_still_lands_on_every_output_with_finite_values():
    # rtol = atol = 0.5 (the largest steps the controller allows, capped by the output points).
    ref = run(PLANT, fidelity="compliant", settings=SimSettings(rtol=1e-12, atol=1e-12), **STEP)
    r = run(PLANT, fidelity="compliant", settings=SimSettings(integrator="rodas", rtol=0.5, atol=0.5), **STEP)
    assert np.array_equal(r.time, ref.time)
    assert np.all(np.isfinite(r.outputs))
    assert np.max(np.abs(r.output("nut_speed") - ref.output("nut_speed"))) < 0.5 * (W300 - ref.output("nut_speed").min())


def test_jit_without_a_working_compiler_falls_back_to_the_same_steps_with_a_warning(tmp_path, monkeypatch):
    import prsa_ctrl.sim.integrators as S

    monkeypatch.setenv("PRSA_CTRL_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setattr(S, "_COMPILED", {})
    # (a plant no other test here compiles: a model's compiled chunk is kept for the process)
    kw = dict(STEP, duration=0.01, fidelity="rigid")
    plant = load_plant("rollerscrew-30x5")
    plain = run(plant, settings=SimSettings(integrator="rodas", rtol=1e-8, atol=1e-8, max_steps=20003), **kw)
    with pytest.warns(UserWarning, match="no-such-cc.* failed .*using CasADi's interpreter"):
        jit = run(plant, settings=SimSettings(integrator="rodas", rtol=1e-8, atol=1e-8, max_steps=20003, jit=True), **kw)
    assert not list((tmp_path / "jit").glob("*.so"))
    assert np.array_equal(jit.outputs, plain.outputs)  # the interpreter: the same arithmetic


def test_a_non_finite_start_ends_in_one_error_after_the_first_chunk_not_nan_outputs():
    seg = _linear_segment(np.array([[-1.0]]), 10, 1e-8)
    with pytest.raises(RuntimeError, match="RODAS4: the state stopped being finite at 0 of the segment"):
        seg(x0=[np.nan], p=[0.0])
    assert seg.stats == {}  # no output of the failed call


def test_a_step_whose_stages_leave_the_domain_is_rejected_not_taken_with_nan():
    # z' = -1e6 z (+ 1e-30 log(z + 0.5): defined for z > -0.5 only; the solution decays to 0 inside
    # it). One step of h = 1 from z = 1: the L-stable stages overshoot below -0.5 (stage 2 is
    # -0.544 z), so the right-hand side is NaN there; the step must be rejected with a shorter step
    # proposed and z kept (was: NaN compared as "finite" and the step accepted with a NaN state).
    z, p, t = ca.SX.sym("z", 1), ca.SX.sym("p", 1), ca.SX.sym("t")
    f = ca.Function("f", [z, p, t], [-1e6 * z + 1e-30 * ca.log(z + 0.5)])
    att = rodas_attempt(f, 1, 1, lu_kernels)
    st1, hit = att([0.0, 1.0, 1.0], [0.0], [1.0, 1e-6, 1e-6])
    st1 = np.asarray(st1).ravel()
    assert st1[0] == 0.0, st1
    assert st1[2] == 1.0, st1
    assert 0 < st1[1] < 1.0, st1
    assert float(hit) == 0.0, st1
    # and a segment from there gets through on shorter steps, finite
    seg = RodasSegment(att.mapaccum("c", CHUNK_ATTEMPTS, [0], [0]), 1, 4, 1e-6, 1e-6, 10**5)
    xs = seg(x0=[1.0], p=[0.0])["xf"]
    assert np.all(np.isfinite(xs))
    assert np.all(np.abs(xs) < 1e-6)
