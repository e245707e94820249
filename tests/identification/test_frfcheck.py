"""identification/frfcheck: the resonances a response shows, its units check, and the FRF path's
refusal of a response with a mode its models lack (a second resonance above the first axial
mode), against chains of inertias written here from their equations of motion."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from prsa_ctrl import load_plant
from prsa_ctrl.errors import FitError
from prsa_ctrl.identification.data import frf_from_arrays
from prsa_ctrl.identification.frfcheck import failure_diagnosis, resonances, unexplained_resonances
from prsa_ctrl.identification.frfplant import fit_frf_structure

TWO_PI = 2 * math.pi


def _base():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant("ballscrew-32x10")


def _chain(f, inertias, springs, zeta=0.03, fc=1000.0, delay_s=0.0):
    """Motor speed / torque of a chain of inertias (kg m^2) joined by torsional springs (N m/rad),
    each spring with a damper of ``2 zeta sqrt(k J_mean)``, the torque through a first-order
    current loop ``fc`` (Hz) and a delay: ``(-w^2 M + j w C + K) x = e1 u``, speed ``j w x_1``."""
    n = len(inertias)
    m = np.diag(inertias)
    k = np.zeros((n, n))
    c = np.zeros((n, n))
    for i, ki in enumerate(springs):
        ci = 2 * zeta * math.sqrt(ki * 0.5 * (inertias[i] + inertias[i + 1]))
        for mat, v in ((k, ki), (c, ci)):
            mat[i, i] += v
            mat[i + 1, i + 1] += v
            mat[i, i + 1] -= v
            mat[i + 1, i] -= v
    out = []
    for fi in f:
        w = TWO_PI * fi
        x = np.linalg.solve(-w * w * m + 1j * w * c + k, np.eye(n)[:, 0])
        out.append(1j * w * x[0])
    g = np.array(out)
    return g / (1 + 1j * f / fc) * np.exp(-1j * TWO_PI * f * delay_s)


def _noisy(g, rel, seed):
    rng = np.random.default_rng(seed)
    return g * np.exp(rel * (rng.standard_normal(len(g)) + 1j * rng.standard_normal(len(g))))


def _three_body(base, f, seed=3):
    """Rotor, coupling-joined screw (a stiff coupling: mode near 900 Hz) and the table on the
    nut's spring (the axial mode near 120 Hz): the base plant's inertia split 30/30/40 %."""
    j = base.reflected_inertia_kg_m2
    j1, j2, j3 = 0.3 * j, 0.3 * j, 0.4 * j
    k_table = j3 * (TWO_PI * 95.0) ** 2
    k_coupling = j1 * j2 / (j1 + j2) * (TWO_PI * 900.0) ** 2
    return _noisy(_chain(f, [j1, j2, j3], [k_coupling, k_table]), 0.01, seed)


def test_resonances_counts_the_modes_of_a_chain_and_none_of_a_rigid_axis():
    base = _base()
    j = base.reflected_inertia_kg_m2
    f = np.geomspace(4.0, 1700.0, 160)
    rigid = frf_from_arrays("r", f, _noisy(_chain(f, [j], [], delay_s=3e-4), 0.01, 1))
    two = frf_from_arrays("t", f, _noisy(_chain(f, [0.6 * j, 0.4 * j], [0.4 * j * (TWO_PI * 100.0) ** 2]), 0.01, 2))
    three = frf_from_arrays("c", f, _three_body(base, f))
    assert resonances(rigid) == []
    (one,) = resonances(two)
    # the undamped mode of two inertias on a spring: f_a sqrt(J / J_m) = 100 sqrt(1 / 0.6)
    assert one["frequency_hz"] == pytest.approx(100.0 / math.sqrt(0.6), rel=0.05)
    found = resonances(three)
    assert len(found) == 2
    m = np.diag([0.3, 0.3, 0.4]) * j
    jj = [0.3 * j, 0.3 * j, 0.4 * j]
    kc, kt = jj[0] * jj[1] / (jj[0] + jj[1]) * (TWO_PI * 900.0) ** 2, jj[2] * (TWO_PI * 95.0) ** 2
    kk = np.array([[kc, -kc, 0], [-kc, kc + kt, -kt], [0, -kt, kt]])
    ev = np.sort(np.sqrt(np.abs(np.linalg.eigvals(np.linalg.solve(m, kk))))) / TWO_PI  # 0, mode 1, mode 2
    for r, fm in zip(found, ev[1:]):
        assert r["frequency_hz"] == pytest.approx(fm, rel=0.08)


def test_fit_refuses_a_response_with_a_second_mode_and_names_it_not_the_units():
    """The chain's second mode is in neither model: no plant, and the line names its frequency,
    never the units (they are right: the low-frequency inertia is the base plant's)."""
    base = _base()
    f = np.geomspace(4.0, 1700.0, 160)
    fr = frf_from_arrays("c", f, _three_body(base, f), sample_time_s=0.0)
    second = resonances(fr)[1]["frequency_hz"]
    for fidelity in (None, "compliant"):
        with pytest.raises(FitError) as info:
            fit_frf_structure([fr], base, fidelity=fidelity)
        msg = str(info.value)
        assert msg.startswith("no plant written: ")
        assert f"{second:.4g} Hz" in msg
        assert "units check passed" in msg
        assert "check the response's units" not in msg
        assert "units check failed" not in msg


def test_two_mass_response_is_not_refused():
    """One axial mode, the model's: nothing left unexplained, a plant is fitted."""
    base = _base()
    j = base.reflected_inertia_kg_m2
    f = np.geomspace(4.0, 1700.0, 160)
    g = _noisy(_chain(f, [0.6 * j, 0.4 * j], [0.4 * j * (TWO_PI * 100.0) ** 2]), 0.01, 2)
    fr = frf_from_arrays("t", f, g, sample_time_s=0.0)
    res, choice = fit_frf_structure([fr], base, refine=False)
    assert choice.structure == "two-mass"
    assert unexplained_resonances([fr], choice.chosen) == []


def test_a_converged_fit_lacking_the_responses_mode_is_refused_with_its_frequency():
    """One resonance, the rigid model fitted to it (as --fidelity compliant's fallback or a failed
    two-mass fit leaves it): the resonance is unexplained, and the line names it and the values the
    fit bent."""
    from prsa_ctrl.identification.frfcheck import unexplained_line
    from prsa_ctrl.identification.twomass import fit_frf_model

    base = _base()
    j = base.reflected_inertia_kg_m2
    f = np.geomspace(4.0, 1700.0, 160)
    fr = frf_from_arrays("t", f, _noisy(_chain(f, [0.6 * j, 0.4 * j], [0.4 * j * (TWO_PI * 100.0) ** 2]), 0.01, 2))
    rigid = fit_frf_model([fr], "rigid")
    (r,) = unexplained_resonances([fr], rigid)
    line = unexplained_line([fr], rigid, [r])
    assert f"{r['frequency_hz']:.4g} Hz" in line
    assert "the rigid model holds none" in line
    two = fit_frf_model([fr], "two-mass")
    assert unexplained_resonances([fr], two) == []


def test_failure_diagnosis_blames_the_units_only_when_their_check_fails():
    base = _base()
    j = base.reflected_inertia_kg_m2
    f = np.geomspace(4.0, 1700.0, 160)
    solver = FitError("rigid FRF fit did not converge: least-squares status 0 (max evaluations) after 4000 "
                      "evaluations; remedy: check the response's units ((rad/s)/(N m))")
    three = frf_from_arrays("c", f, _three_body(base, f))
    line = failure_diagnosis([three], j, solver)
    assert "units check passed" in line
    assert "check the response's units" not in line
    assert "2 resonances" in line
    in_deg = frf_from_arrays("d", f, _three_body(base, f) * 180 / math.pi)
    assert "units check failed" in failure_diagnosis([in_deg], j, solver)
    rigid = frf_from_arrays("r", f, _noisy(_chain(f, [j], []), 0.01, 1))
    line = failure_diagnosis([rigid], j, solver)
    assert "a failure of the solver" in line
    assert "units check passed" in line


def test_the_suggested_band_keeps_the_first_mode_and_leaves_the_second_out():
    """The band the refusal names (frfcheck.suggested_band) on the chain of three inertias: from
    at most its lowest point, over the first mode and its anti-resonance, below the second mode's
    notch; cut there, the response shows the first resonance alone."""
    from prsa_ctrl.identification.frfcheck import suggested_band

    base = _base()
    f = np.geomspace(4.0, 1700.0, 160)
    g = _three_body(base, f)
    fr = frf_from_arrays("c", f, g)
    found = resonances(fr)
    lo, hi = suggested_band(fr, found)
    assert lo <= f[0]
    assert lo > 0.99 * f[0]
    y = f * np.abs(g)
    between = (f > found[0]["frequency_hz"]) & (f < found[1]["frequency_hz"])
    notch = f[between][np.argmin(y[between])]  # the second mode's anti-resonance
    assert 1.5 * found[0]["frequency_hz"] < hi <= notch
    assert hi <= math.sqrt(found[0]["frequency_hz"] * found[1]["frequency_hz"])
    m = (f >= lo) & (f <= hi)
    (one,) = resonances(frf_from_arrays("cut", f[m], g[m]))
    assert one["frequency_hz"] == found[0]["frequency_hz"]
    # the refusal of the whole response names it as the flag to type
    with pytest.raises(FitError, match=rf"--frf-band {lo:g},{hi:g}$"):
        fit_frf_structure([fr], base)


def test_one_resonance_seen_in_two_records_counts_once():
    """The logs' own responses come one per log, all of the same axis: a mode each of them shows
    is one resonance. On main the second generator's feed axis (multisine and staircase responses
    both peaking at 110.8 Hz) was refused as showing two, "up to the geometric mean of 110.8 and
    110.8 Hz". Two records of one two-mass axis (different noise, the second record's mode 2 %
    lower, as a mode moves with the nut force) give one resonance, the more prominent peak; two
    distinct modes in two records stay two; and two peaks within one record are never merged."""
    from prsa_ctrl.identification.frfcheck import SAME_RESONANCE

    base = _base()
    j = base.reflected_inertia_kg_m2
    f = np.geomspace(4.0, 1700.0, 160)
    k = 0.4 * j * (TWO_PI * 100.0) ** 2
    a = frf_from_arrays("a", f, _noisy(_chain(f, [0.6 * j, 0.4 * j], [k]), 0.01, 5))
    b = frf_from_arrays("b", f, _noisy(_chain(f, [0.6 * j, 0.4 * j], [0.96 * k]), 0.01, 6))
    alone = resonances(a)[0]["frequency_hz"], resonances(b)[0]["frequency_hz"]
    assert abs(alone[0] / alone[1] - 1) <= SAME_RESONANCE
    both = resonances([a, b])
    assert len(both) == 1
    top = max((resonances(a)[0], resonances(b)[0]), key=lambda r: r["height_db"])
    assert both[0] == top
    far = frf_from_arrays("far", f, _noisy(_chain(f, [0.6 * j, 0.4 * j], [9 * k]), 0.01, 7))  # mode 3 x higher
    assert len(resonances([a, far])) == 2
    assert len(resonances([frf_from_arrays("c", f, _three_body(base, f)), a])) == 2  # its two, a's merged with one
