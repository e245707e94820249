"""prsa_ctrl.identification.warmstart: a fit's states carried to another fit of the same records
(other segments, a subset of the records) start it where the first one ended, and the fit
reaches the same optimum as from the reference, in fewer iterations."""

from dataclasses import replace

import numpy as np
import pytest

from prsa_ctrl.identification import timedomain as td
from prsa_ctrl.identification.common import key_bounds
from prsa_ctrl.identification.gaussnewton import condense
from prsa_ctrl.identification.synthetic import fit_record
from prsa_ctrl.identification.warmstart import initial_states, states_of

KEYS = ("nut.inertia_kg_m2", "friction.efficiency", "friction.viscous_n_m_s_per_rad")


@pytest.fixture(scope="module")
def two():
    rec, truth = fit_record(0.5)
    n = rec.n // 2

    def part(name, sl):
        return replace(rec, name=name, time_s=rec.time_s[sl], torque_command_n_m=rec.torque_command_n_m[sl],
                       nut_angle_rad=rec.nut_angle_rad[sl], axial_load_n=rec.axial_load_n[sl],
                       nut_speed_rad_s=None if rec.nut_speed_rad_s is None else rec.nut_speed_rad_s[sl])

    return part("a", slice(0, n)), part("b", slice(n, rec.n)), truth


def _problem(records, plant, segment_s):
    ts = records[0].sample_time_s
    b = [key_bounds(plant, k, ts) for k in KEYS]
    scales = np.array([x[2] for x in b])
    lo, hi = np.array([x[0] for x in b]) / scales, np.array([x[1] for x in b]) / scales
    s0 = np.array([plant.values[k] for k in KEYS]) / scales
    return td._Problem(plant, KEYS, scales, "rigid", records, ts, segment_s, 0), s0, lo, hi


def test_states_round_trip_and_reach_other_segments_and_a_subset(two):
    a, b, truth = two
    p, s0, lo, hi = _problem([a, b], truth, 0.05)
    sol = p.solve(s0, lo, hi, 30, 1e-8, fixed=False)
    st = states_of(p, sol["V"], sol["X0"])
    assert set(st) == {"a", "b"}
    V, X0 = initial_states(p, st)
    np.testing.assert_allclose(V, sol["V"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(X0, sol["X0"], rtol=0, atol=1e-9)
    # another problem: record b alone on shorter segments -- its states at every sample it covers
    q, *_ = _problem([b], truth, 0.02)
    Vq, X0q = initial_states(q, st)
    got = states_of(q, Vq, X0q)["b"]
    k_b, x_b = st["b"]
    cover = np.all(np.isfinite(got[0]), axis=(0, 1))
    assert cover.any()
    np.testing.assert_allclose(got[0][:, :, cover], k_b[:, :, cover], rtol=1e-12, atol=1e-12)
    # a state the first fit left out (NaN) starts from the reference: no NaN enters a start
    assert np.all(np.isfinite(Vq))
    assert np.all(np.isfinite(X0q))
    # nothing to carry: no warm start
    assert initial_states(q, {}) is None
    assert initial_states(q, {"other": st["a"]}) is None


def test_a_refit_on_a_subset_from_the_fits_states_reaches_the_same_optimum_in_fewer_iterations(two):
    a, b, truth = two
    start = truth.with_params({"nut.inertia_kg_m2": 1.3 * truth.values["nut.inertia_kg_m2"]})
    p, s0, lo, hi = _problem([a, b], start, 0.05)
    full = p.solve(s0, lo, hi, 30, 1e-8, fixed=False)
    st = states_of(p, full["V"], full["X0"])
    q, _, lo_q, hi_q = _problem([b], start, 0.05)
    cold = q.solve(full["s"], lo_q, hi_q, 30, 1e-8, fixed=False)
    # (states that solve the same segments' equations: no state-only warm-up, as the fit takes them)
    warm = q.solve(full["s"], lo_q, hi_q, 30, 1e-8, fixed=False, init=initial_states(q, st), warm=0)
    assert cold["status"] == warm["status"] == "converged"
    assert warm["iterations"] < cold["iterations"]
    # the same optimum: within a thousandth of a standard error of each key
    js, rv, _ = condense(q.linearise(cold["V"], cold["X0"], cold["s"])[1])
    _, se, _ = q._param_step(js, rv, cold["s"], lo_q, hi_q, 0.3)
    assert np.all(np.abs(warm["s"] - cold["s"]) < 1e-3 * se)
    assert warm["objective"] == pytest.approx(cold["objective"], rel=1e-9)
