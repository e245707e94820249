"""The fixed-step Radau IIA integrator of the sampled loop (SimSettings(integrator="radau")):
its error against a tight CVODES reference on the paper load step and on a reversal through
stiction, convergence with the step, determinism, no NaN, and its settings' validation."""

import numpy as np
import pytest

from prsa_ctrl import PID, load_plant
from prsa_ctrl.sim.integrators import SimSettings
from prsa_ctrl.sim.engine import energy_balance, fast_settings, fixed_step_error, run

PLANT = load_plant()
W300 = 31.41592653589793
REF = SimSettings(rtol=1e-10, atol=1e-10)
FAST = SimSettings(integrator="radau")
#: The paper scene's accuracy (tuning/paper-load-step.toml): 1 % of the peak drop.
ACCURACY = 0.01
STEP = dict(setpoint=W300, load=[(0.0, 500.0), (0.0025, 1500.0)], duration=0.05, controller=PID(0.0849, 14.67),
            discrete=True)
#: Reversal from +1 to -1 rad/s: the nut crosses Karnopp's stick band (|w| < 0.003 rad/s).
REVERSAL = dict(setpoint=[(0.0, 1.0), (0.02, -1.0)], load=500.0, duration=0.12, controller=PID(0.085, 14.7),
                discrete=True)
#: Setpoint +0.05 then -0.05 rad/s: the sampled loop stops the nut and stiction holds it at rest.
STICK = dict(REVERSAL, setpoint=[(0.0, 0.05), (0.02, -0.05)])


@pytest.fixture(scope="module")
def step_reference():
    return run(PLANT, fidelity="compliant", settings=REF, **STEP).output("nut_speed")


def _err(settings, ref, fidelity="compliant", **kw):
    w = run(PLANT, fidelity=fidelity, settings=settings, **kw).output("nut_speed")
    assert np.all(np.isfinite(w))
    return float(np.max(np.abs(w - ref)))


def test_load_step_error_is_inside_the_scene_accuracy_and_converges(step_reference):
    drop = W300 - step_reference.min()
    assert drop > 2.0  # a real load step
    e4 = _err(FAST, step_reference, **STEP)
    e8 = _err(SimSettings(integrator="radau", substeps=8), step_reference, **STEP)
    assert e4 <= ACCURACY * drop, (e4, drop)
    # third order: halving the step cuts the error by ~2**3 (4 allows for the quantised encoder)
    assert e8 < e4 / 4, (e4, e8)
    # more stages and Newton iterations also converge towards the reference
    e3 = _err(SimSettings(integrator="radau", stages=3, newton=2), step_reference, **STEP)
    assert e3 < e4


def test_an_implicit_euler_step_is_first_order_and_worse(step_reference):
    e1 = _err(SimSettings(integrator="radau", stages=1), step_reference, **STEP)
    e2 = _err(FAST, step_reference, **STEP)
    assert e1 > 2 * e2


@pytest.mark.parametrize("fidelity", ["rigid", "compliant"])
def test_reversal_through_stiction(fidelity):
    ref = run(PLANT, fidelity=fidelity, settings=REF, **REVERSAL).output("nut_speed")
    r = run(PLANT, fidelity=fidelity, settings=FAST, energy=True, **REVERSAL)
    w = r.output("nut_speed")
    assert np.all(np.isfinite(r.states))
    assert np.all(np.isfinite(r.outputs))
    assert ref[-1] == pytest.approx(-1.0, abs=0.01)
    assert w[-1] == pytest.approx(-1.0, abs=0.01)
    assert np.max(np.abs(w - ref)) <= ACCURACY * 2.0  # 1 % of the 2 rad/s reversal
    assert energy_balance(r)["relative_residual"] < 1e-4


@pytest.mark.parametrize("fidelity", ["rigid", "compliant"])
def test_stiction_holds_the_nut_at_rest_as_in_the_reference(fidelity):
    ref = run(PLANT, fidelity=fidelity, settings=REF, **STICK).output("nut_speed")
    w = run(PLANT, fidelity=fidelity, settings=FAST, **STICK).output("nut_speed")
    assert np.all(np.isfinite(w))
    stuck = np.abs(ref) < 1e-9
    assert stuck[-100:].all()
    assert np.all(np.abs(w[-100:]) < 1e-9)  # stuck at exactly zero speed
    assert np.max(np.abs(w - ref)) <= ACCURACY * 0.05


def test_fixed_step_runs_are_deterministic():
    a = run(PLANT, fidelity="compliant", settings=FAST, **STEP)
    b = run(PLANT, fidelity="compliant", settings=SimSettings(integrator="radau"), **STEP)
    assert np.array_equal(a.outputs, b.outputs)
    assert np.array_equal(a.states, b.states)
    assert a.info["integrator"] == "radau"


def test_continuous_mode_fixed_step_is_close_to_the_reference():
    kw = dict(STEP, discrete=False, dt=1e-4, duration=0.02)
    ref = run(PLANT, fidelity="compliant", settings=REF, **kw).output("nut_speed")
    w = run(PLANT, fidelity="compliant", settings=FAST, **kw).output("nut_speed")
    assert np.all(np.isfinite(w))
    assert w.shape == ref.shape
    assert np.max(np.abs(w - ref)) <= ACCURACY * (W300 - ref.min())


def test_fast_settings_chooses_by_measured_error():
    chosen, m = fast_settings(PLANT, ACCURACY, fidelity="rigid", **STEP)
    assert chosen == FAST
    assert m["relative"] < 0.5 * ACCURACY
    # an implicit Euler step with one substep is too coarse for a 0.1 % accuracy
    coarse = SimSettings(integrator="radau", stages=1, substeps=1)
    chosen, m = fast_settings(PLANT, 0.001, coarse, fidelity="compliant", **STEP)
    assert chosen is None
    assert m["relative"] > 0.0005
    assert fixed_step_error(PLANT, FAST, fidelity="rigid", **STEP)["max_error_rad_s"] >= 0.0
    with pytest.raises(ValueError, match="accuracy = 2"):
        fast_settings(PLANT, 2, fidelity="rigid", **STEP)


@pytest.mark.parametrize("kwargs, match", [
    ({"stages": 4}, "stages = 4"),
    ({"substeps": 0}, "substeps = 0"),
    ({"substeps": 2.5}, "substeps = 2.5"),
    ({"newton": 0}, "newton = 0"),
    ({"integrator": "rk4"}, "integrator = 'rk4'"),
    ({"jit": 1}, "jit = 1"),
    ({"substeps": 4, "jacobian_every": 3}, "jacobian_every = 3; expected a divisor of substeps = 4"),
    ({"substeps": 4, "jacobian_every": 8}, "jacobian_every = 8"),
    ({"jacobian_every": 0}, "jacobian_every = 0"),
    ({"jacobian_every": True}, "jacobian_every = True"),
])
def test_bad_fixed_step_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SimSettings(**kwargs)


# --- compiled right-hand side (SimSettings(jit=True)) ----------------------------------------

def test_jit_runs_the_same_equations_from_a_per_user_cache(tmp_path, monkeypatch):
    import prsa_ctrl.sim.integrators as S

    monkeypatch.setenv("PRSA_CTRL_CACHE", str(tmp_path))
    monkeypatch.setattr(S, "_COMPILED", {})
    kw = dict(STEP, discrete=False, dt=1e-4, duration=0.01, fidelity="rigid")
    plain = run(PLANT, settings=SimSettings(rtol=1e-8, atol=1e-8), **kw)
    jit = run(PLANT, settings=SimSettings(rtol=1e-8, atol=1e-8, jit=True), **kw)
    libs = list((tmp_path / "jit").glob("prsa_ode_*.so"))
    assert len(libs) == 1  # compiled once, into the cache, keyed by the code's hash
    np.testing.assert_allclose(jit.outputs, plain.outputs, rtol=1e-9, atol=1e-9)
    # a second process-level build finds the library instead of compiling again
    monkeypatch.setattr(S, "_COMPILED", {})
    mtime = libs[0].stat().st_mtime_ns
    again = run(PLANT, settings=SimSettings(rtol=1e-8, atol=1e-8, jit=True, max_steps=20001), **kw)
    assert libs[0].stat().st_mtime_ns == mtime
    assert np.array_equal(again.outputs, jit.outputs)


def test_jit_without_a_compiler_falls_back_with_a_note(tmp_path, monkeypatch):
    import prsa_ctrl.sim.integrators as S

    monkeypatch.setenv("PRSA_CTRL_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setattr(S, "_COMPILED", {})
    kw = dict(STEP, discrete=False, dt=1e-4, duration=0.01, fidelity="rigid")
    with pytest.warns(UserWarning, match="using CasADi's interpreter"):
        r = run(PLANT, settings=SimSettings(rtol=1e-8, atol=1e-8, jit=True, max_steps=20002), **kw)
    plain = run(PLANT, settings=SimSettings(rtol=1e-8, atol=1e-8), **kw)
    assert np.array_equal(r.outputs, plain.outputs)
    assert not list((tmp_path / "jit").glob("*.so"))
