"""The margins of a tuning result are the true crossings (issue 25, prsa-pid reports them): the
gain crossover, phase margin and gain margin of ``TuningResult.margins`` agree with crossings
found here by root finding (scipy.optimize.brentq) on the loop's exact frequency response, the
delay as ``exp(-j w L)``. Before the crossings were polished the crossover came from linear
interpolation on the peak grid and was off by up to ~1.6e-4 relative."""

import math

import control
import numpy as np
import pytest
from scipy.optimize import brentq

from prsa_ctrl.tuning import tune_pid


def _loop(num, den, delay, kp, ki, kd, tf):
    def L(w):
        s = 1j * np.asarray(w, float)
        c = kp + ki / s + (kd * s / (tf * s + 1) if tf else kd * s)
        return np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * delay) * c
    return L


def _crossings(L, w):
    """(crossover rad/s, PM deg, GM dB) by brentq between the bracketing points of a dense grid."""
    v = L(w)
    lm = np.log(np.abs(v))
    i = np.flatnonzero(np.sign(lm[:-1]) != np.sign(lm[1:]))
    wcs = [brentq(lambda x: math.log(abs(L([x])[0])), w[k], w[k + 1], xtol=1e-15, rtol=1e-15) for k in i]
    pms = [math.degrees(np.angle(L([x])[0])) % 360 - 180 for x in wcs]  # 180 + angle, folded to (-180, 180]
    j = int(np.argmin(np.abs(pms)))
    # phase crossings: Im L = 0 with Re L < 0
    im = np.imag(v)
    k = np.flatnonzero((np.sign(im[:-1]) != np.sign(im[1:])) & (np.real(v[:-1]) < 0))
    gms = [-20 * math.log10(abs(L([brentq(lambda x: float(np.imag(L([x])[0])), w[q], w[q + 1],
                                          xtol=1e-15, rtol=1e-15)])[0])) for q in k]
    return wcs[j], pms[j], (min(gms) if gms else math.inf)


@pytest.mark.parametrize("num, den, delay, kw", [
    ([1.0], [1.0, 1.0], 1.0, {"controller": "pi"}),  # exact delay: many phase crossings
    ([1.0], [1.0, 3.0, 3.0, 1.0], 0.0, {"controller": "pid", "ideal": True, "objective": "ie"}),
    ([1.0], [1.0, 3.0, 3.0, 1.0], 0.0, {"controller": "pid", "objective": "iae"}),
])
def test_margins_are_the_true_crossings(num, den, delay, kw):
    r = tune_pid(control.tf(num, den), delay=delay, **kw)
    p = r.pid
    tf = 0.0 if kw.get("ideal") else p.tf
    L = _loop(num, den, delay, p.kp, p.ki, p.kd, tf)
    wc, pm, gm = _crossings(L, np.logspace(-4, 4, 400_001))
    m = r.margins[0]
    assert m.wc_rad_s == pytest.approx(wc, rel=1e-9)
    assert m.pm_deg == pytest.approx(pm, abs=1e-7)
    if math.isfinite(gm):
        assert m.gm_db == pytest.approx(gm, abs=1e-7)
    else:
        assert m.gm_db == math.inf
