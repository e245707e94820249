"""An independent closed-loop linear-axis log generator (numpy only: nothing of prsa_ctrl's
models): fine trapezoidal substeps with a Karnopp stick band, quantised position, the
position-P/velocity-P controller with the two-sample average, and the log description of its
CSV in mm and ms. The linear-axis fit's tests (tests/identification/test_axis.py) fit its logs;
tests/identification/test_axistwomass.py drives its profile.
"""

from __future__ import annotations

import math

import numpy as np

from prsa_ctrl.identification.axis import DEFAULTS, LinearAxisPlant

#: The generator's axis and controller: M kg, Fv+ Fv- N s/m, Fc+ Fc- N; position and velocity gains, drive
#: gain N/V, sample time s, encoder resolution m.
TRUTH = (80.0, 150.0, 220.0, 15.0, 25.0)
KP, KV, GAIN, H, RES = 150.0, 250.0, 30.0, 1e-3, 5e-8


def trapezoid(dist, vmax, amax):
    """The distance covered (m) at each sample of a move of ``dist`` m at speed ``vmax`` m/s and
    acceleration ``amax`` m/s^2 (a triangle when ``dist`` is too short to reach ``vmax``), from 0 to
    ``dist``."""
    ta = vmax / amax
    if dist < vmax * ta:
        ta = math.sqrt(dist / amax)
        vmax = amax * ta
    tc = (dist - vmax * ta) / vmax
    total = 2 * ta + tc
    tt = np.arange(int(total / H) + 1) * H
    return np.where(tt < ta, 0.5 * amax * tt ** 2, np.where(tt < ta + tc, 0.5 * amax * ta ** 2 + vmax * (tt - ta),
                                                           dist - 0.5 * amax * np.clip(total - tt, 0, None) ** 2))


def profile(rng, n):
    """Bang-bang acceleration moves between random positions in both directions, with rests."""
    r = np.zeros(n)
    x, k = 0.0, 0
    while k < n:
        target = rng.uniform(0.0, 0.2)
        vmax, amax = rng.uniform(0.03, 0.12), rng.uniform(0.5, 2.0)
        seg = x + math.copysign(1.0, target - x) * trapezoid(abs(target - x), vmax, amax)
        take = min(seg.size, n - k)
        r[k:k + take] = seg[:take]
        k += take
        x = seg[take - 1]
        rest = int(rng.uniform(0.1, 0.3) / H)
        r[k:k + rest] = x
        k += rest
    return r[:n]


def closed_loop_log(seed, n=6000, sub=40, pulses=None):
    """Independent closed-loop generator (not the library's exact solution); ``pulses`` (V) is
    added to the controller output at the drive input and is part of the logged command."""
    rng = np.random.default_rng(seed)
    m, fvp, fvn, fcp, fcn = TRUTH
    r = profile(rng, n)
    x = v = 0.0
    qm, u = np.zeros(n), np.zeros(n)
    qprev = qfprev = 0.0
    hs = H / sub
    for k in range(n):
        qk = RES * math.floor(x / RES + 0.5)
        qm[k] = qk
        qf = 0.5 * (qk + qprev)
        dq = (qf - qfprev) / H
        qprev, qfprev = qk, qf
        u[k] = min(10.0, max(-10.0, KV * (KP * (r[k] - qk) - dq))) + (0.0 if pulses is None else pulses[k])
        f = GAIN * u[k]
        for _ in range(sub):
            if v > 0:
                a = (f - fcp - fvp * v) / m
            elif v < 0:
                a = (f + fcn - fvn * v) / m
            else:
                a = (f - fcp) / m if f > fcp else ((f + fcn) / m if f < -fcn else 0.0)
            vn = v + hs * a
            if v != 0 and vn * v < 0:  # stops inside the substep (Karnopp: stays stopped for its rest)
                x += 0.5 * v * (-v / a)
                v = 0.0
                continue
            x += 0.5 * (v + vn) * hs
            v = vn
    return np.arange(n) * H, qm, r, u


CSV_FORMAT = """format = "csv"
[time]
name = "time_ms"
unit = "ms"
[position]
name = "pos_mm"
unit = "mm"
resolution = 5e-5
[reference]
name = "ref_mm"
unit = "mm"
[command]
name = "u_V"
unit = "V"
gain = 30.0
[controller]
structure = "position-p/velocity-p"
kp = 150.0
kv = 250.0
saturation = 10.0
sample_time_s = 0.001
check_tolerance = 1e-6
"""


#: :data:`CSV_FORMAT` plus the column of the drive's test signal (``dither_V``), for logs written
#: by :func:`write_dither_csv`.
DITHER_CSV_FORMAT = CSV_FORMAT.replace("[controller]", '[test_signal]\nname = "dither_V"\nunit = "V"\n[controller]')


def write_dither_csv(path, arrays):
    """Write ``(time_s, position_m, reference_m, command_V, dither_V)`` as a CSV in the units of
    :data:`DITHER_CSV_FORMAT` (ms, mm, V)."""
    t, q, r, u, d = arrays
    rows = ["time_ms,pos_mm,ref_mm,u_V,dither_V"]
    rows += [f"{a * 1e3:.6f},{b * 1e3:.9f},{c * 1e3:.9f},{float(e)!r},{float(g)!r}" for a, b, c, e, g in zip(t, q, r, u, d)]
    path.write_text("\n".join(rows) + "\n")


def placeholder_base():
    """The linear-axis defaults with a placeholder mass of 1 kg: the base a fit of these logs starts from."""
    vals = {k: v for k, (v, _) in DEFAULTS.items()}
    srcs = {k: s for k, (_, s) in DEFAULTS.items()}
    vals["axis.mass_kg"], srcs["axis.mass_kg"] = 1.0, "test: placeholder"
    return LinearAxisPlant("base", vals, srcs)
