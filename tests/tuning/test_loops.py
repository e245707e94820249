"""prsa_ctrl.tuning.loops: the error sums to infinity are bounded in work (issue 31: a filter
just below Nyquist put a closed-loop pole next to z = -1; the Lyapunov solve failed its residual
check and the fallback summed up to 2^22 samples one by one on every call, inside block_sum's
loop: prsa-tune ran for minutes). Work is counted (doublings, calls), never timed."""

import math

import numpy as np
import pytest
import scipy.linalg

from prsa_ctrl.tuning import loops
from prsa_ctrl.tuning.settings import TAIL_MAX_STEPS


def _pair(eps):
    """A 2-state loop with a pole at -(1 - eps) and one at 0.5, and its output row."""
    return np.array([[-(1.0 - eps), 1.0], [0.0, 0.5]]), np.array([1.0, 0.3])


def _closed_form(a, c):
    """sum_k (a^k)' c' c a^k from the eigen-decomposition a = V diag(l) V^-1 (independent of
    both the Lyapunov solver and the doubling): with r = c V, W = V^-1,
    P = W' [r_i r_j / (1 - l_i l_j)] W."""
    lam, v = np.linalg.eig(a)
    w = np.linalg.inv(v)
    r = c @ v
    m = np.outer(r, r) / (1.0 - np.outer(lam, lam))
    return np.real(w.T @ m @ w)


def test_budget_is_the_tail_budget():
    assert 2 ** loops.GRAMIAN_DOUBLINGS == TAIL_MAX_STEPS


@pytest.mark.parametrize("eps", [1e-2, 1e-4, 1e-5])
def test_series_gramian_is_exact_and_bounded_near_minus_one(eps):
    a, c = _pair(eps)
    p, d = loops._series_gramian(a, c)
    ref = _closed_form(a, c)
    assert np.max(np.abs(p - ref)) <= 1e-10 * np.max(np.abs(ref))
    # the work: doublings until ||a^N||^2 <= 1e-16, N = 2^d, i.e. about log2(37/eps) - 1
    assert d <= loops.GRAMIAN_DOUBLINGS
    assert d == math.ceil(math.log2(math.log(1e-16) / (2 * math.log(1 - eps)))) or \
        d == math.ceil(math.log2(math.log(1e-16) / (2 * math.log(1 - eps)))) + 1


def test_series_gramian_refuses_a_pole_too_near_the_unit_circle_after_the_cap(monkeypatch):
    a, c = _pair(1e-7)
    calls = []
    real_norm = np.linalg.norm
    # count the doublings through the convergence test (one 2-norm of a^N per doubling)
    monkeypatch.setattr(np.linalg, "norm", lambda *args, **kw: calls.append(1) or real_norm(*args, **kw))
    with pytest.raises(loops._TailBudgetError, match=r"pole at \|z\| = 0\.9999999, within 1e-07 of the unit "
                                                    r"circle.*2\^22 samples"):
        loops._series_gramian(a, c)
    assert len(calls) == loops.GRAMIAN_DOUBLINGS


def test_gramian_fallback_runs_once_and_bounded(monkeypatch):
    """The Lyapunov solve made to fail its residual check (as it did for the near-Nyquist
    notch): the fallback is summed ONCE per block_sum, by doubling, and agrees with the closed
    form; the block sum itself stops within its block budget."""
    a, c = _pair(1e-4)
    monkeypatch.setattr(scipy.linalg, "solve_discrete_lyapunov", lambda a, q: np.full(a.shape, np.nan))
    seen = []
    real = loops._series_gramian
    monkeypatch.setattr(loops, "_series_gramian", lambda ab, cb: seen.append(real(ab, cb)[1]) or real(ab, cb))
    g = loops._gramian(a, c)
    z = np.array([0.7, -0.2])
    ref = _closed_form(a, c)
    assert g(z) == pytest.approx(float(z @ ref @ z), rel=1e-10)
    assert len(seen) == 1
    assert seen[0] <= loops.GRAMIAN_DOUBLINGS
    # block_sum: one Gramian for the whole sum (it was one series of up to 2^22 steps per block)
    seen.clear()
    val, tail = loops.block_sum(a, c, z, 0, 0.0, 1e-3, "iae", 1e-6)
    assert len(seen) == 1
    assert math.isfinite(val)
    assert tail <= 1e-6 * val
    # and the IAE equals a direct sum of |c a^k z| (the tail past 2e6 samples is < 1e-30)
    x, direct = z.copy(), 0.0
    for _ in range(200_000):
        direct += abs(c @ x)
        x = a @ x
    assert val == pytest.approx(1e-3 * direct, rel=1e-6)


def test_block_sum_of_a_loop_beyond_the_budget_is_marginal(monkeypatch):
    """A pole within 1e-7 of z = -1: the tail cannot be bounded within 2^22 samples; block_sum
    says (inf, inf) (as for a marginal loop) after the capped doublings, not minutes later."""
    a, c = _pair(1e-7)
    monkeypatch.setattr(scipy.linalg, "solve_discrete_lyapunov", lambda a, q: np.full(a.shape, np.nan))
    seen = []
    real = loops._series_gramian

    def spy(ab, cb):
        seen.append(1)
        return real(ab, cb)

    monkeypatch.setattr(loops, "_series_gramian", spy)
    assert loops.block_sum(a, c, np.array([1.0, 0.0]), 0, 0.0, 1e-3, "iae", 1e-6) == (math.inf, math.inf)
    assert seen == [1]


def test_peak_sensitivity_is_the_margins_ms_exactly(paper_plant):
    """The baselines' Kp sweep screens by ``peak_sensitivity``: the same number as
    ``margins(g).ms`` (not an approximation of it), on gains from sluggish to nearly unstable."""
    import warnings

    from prsa_ctrl.studies.autotune import actuator_loops
    from prsa_ctrl.studies.scene import load_scene

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lp = actuator_loops(paper_plant, load_scene())[0]
    checked = 0
    for kp in 0.085 * np.logspace(-1, 0.6, 9):
        for ki in (1.47, 14.7):
            g = (kp, ki, 0.0)
            if not lp.is_stable(g):
                continue
            assert lp.peak_sensitivity(g) == lp.margins(g).ms
            checked += 1
    assert checked >= 12


def test_sensitivity_peaks_are_the_margins_ms_and_mt_exactly(paper_plant):
    """The Monte Carlo's and the robust summary's Ms/Mt come from ``sensitivity_peaks``: the
    same numbers as ``margins(g).ms`` and ``.mt`` (not approximations), on gains from sluggish
    to nearly unstable, and they move with the gains."""
    import warnings

    from prsa_ctrl.studies.autotune import actuator_loops
    from prsa_ctrl.studies.scene import load_scene

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lp = actuator_loops(paper_plant, load_scene())[0]
    seen = set()
    for kp in 0.085 * np.logspace(-1, 0.6, 7):
        for ki in (1.47, 14.7):
            g = (kp, ki, 0.0)
            if not lp.is_stable(g):
                continue
            m = lp.margins(g)
            assert lp.sensitivity_peaks(g) == (m.ms, m.mt)
            seen.add(m.ms)
    assert len(seen) >= 8


def _gradient_loops():
    """Loop models of every kind the gradient must handle, each with gains that stabilise it:
    continuous PID and PI (a Pade delay in the plant), the sampled drive loop with the encoder's
    speed and with a Kalman filter's (a denominator part and the load feed-forward gain)."""
    import control

    import hand_loop as hl  # tests/tuning is on sys.path
    from prsa_ctrl.tuning.builders import continuous_loop, drive_loop
    from prsa_ctrl.tuning.loopmeasure import KalmanEstimate

    lag3 = continuous_loop(control.tf([1.0], [1.0, 3.0, 3.0, 1.0]), tf=0.05, horizon=20.0)
    delayed = continuous_loop(control.tf([1.0], [1.0, 1.0]), tf=0.05, horizon=20.0, delay=0.5)
    encoder = drive_loop(hl.A, hl.B, hl.C_SPEED, hl.ANGLE, ts=hl.TS, speed_filter=2 * hl.TS, tf=hl.TF, horizon=0.02,
                         step=hl.STEP)
    kalman = drive_loop(hl.A, hl.B, hl.C_SPEED, hl.ANGLE, ts=hl.TS, tf=hl.TF, horizon=0.02, step=hl.STEP,
                        command_delay_samples=1, measurement=KalmanEstimate(hl.toy_kf(), True))
    return [(lag3, (2.3, 1.7, 2.3)), (delayed, (0.9, 1.1, 0.0)), (encoder, (0.3, 15.0, 2e-4)),
            (kalman, (0.2, 8.0, 0.0, 0.4))]


@pytest.mark.parametrize("case", range(4))
@pytest.mark.parametrize("key", ["ms", "mt", "mks"])
def test_magnitude_gradient_is_the_central_difference_at_fixed_frequency(case, key):
    """``magnitude_gradient`` (closed form, what Tuner._polish differentiates its peaks with)
    against central differences of ``_magnitude``'s value (``noise_response`` for mks) at 40
    fixed frequencies over the loop's range, per gain, to 1e-6 of the largest slope."""
    lp, gains = _gradient_loops()[case]
    g = lp.gvec(gains)
    assert lp.stability(g) == "stable"
    w = np.logspace(math.log10(lp.omega[0]), math.log10(lp.omega[-1]), 40)

    def mag(gv):
        if key == "mks":
            return np.abs(lp.noise_response(gv, w))
        L = lp.loop_response(gv, w)
        return 1 / np.abs(1 + L) if key == "ms" else np.abs(L / (1 + L))

    fd = np.empty((lp.n_gains, w.size))
    for i in range(lp.n_gains):
        d = 1e-6 * max(abs(g[i]), 1e-3)
        e = np.zeros(lp.n_gains)
        e[i] = d
        fd[i] = (mag(g + e) - mag(g - e)) / (2 * d)
    an = lp.magnitude_gradient(g, key, w)
    assert an.shape == (lp.n_gains, w.size)
    np.testing.assert_allclose(an, fd, rtol=0, atol=1e-6 * float(np.max(np.abs(fd))))


@pytest.mark.parametrize("case", [0, 2, 3])
def test_magnitude_gradient_at_the_peak_is_the_peaks_derivative(case):
    """At the frequency of the true peak of |S| (``peaks``), the closed-form derivative is that of
    the peak itself, re-searched at each perturbed gain (Danskin), to 1e-5 relative per gain."""
    lp, gains = _gradient_loops()[case]
    g = lp.gvec(gains)
    pk = lp.peaks(g, mt=False)
    an = lp.magnitude_gradient(g, "ms", np.array([pk["w_ms"]]))[:, 0]
    for i in range(lp.n_gains):
        if g[i] == 0.0:
            continue
        e = np.zeros(lp.n_gains)
        e[i] = 1e-5 * g[i]
        fd = (lp.peaks(g + e, mt=False)["ms"] - lp.peaks(g - e, mt=False)["ms"]) / (2e-5 * g[i])
        assert an[i] == pytest.approx(fd, rel=1e-5, abs=1e-9 * abs(pk["ms"] / g[i]))


def test_magnitude_gradient_refuses_an_unknown_key():
    lp, gains = _gradient_loops()[0]
    with pytest.raises(ValueError, match="key = 'ks'"):
        lp.magnitude_gradient(gains, "ks", np.array([1.0]))
