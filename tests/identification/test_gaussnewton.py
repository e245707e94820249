"""prsa_ctrl.identification.gaussnewton: the convergence rule of a stalled Gauss-Newton
iteration (a first-order point within the noise converges, any other point does not), on a
synthetic linear least-squares problem whose optimum and standard errors are known exactly."""

import math

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from prsa_ctrl.identification import gaussnewton as gn


def _problem(seed=0, n=400):
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n, 3)) * np.array([1.0, 30.0, 0.01])  # badly scaled columns
    y = a @ np.array([1.0, -2.0, 50.0]) + 0.3 * rng.standard_normal(n)
    x_opt = np.linalg.lstsq(a, y, rcond=None)[0]
    dof = n - 3
    s2 = float((a @ x_opt - y) @ (a @ x_opt - y)) / dof
    cov = s2 * np.linalg.inv(a.T @ a)
    return a, y, x_opt, cov, dof


def se_scale(cov):
    return float(np.sqrt(np.max(np.diag(cov))))


def s2_opt(a, y, x_opt, dof):
    return float((a @ x_opt - y) @ (a @ x_opt - y)) / dof


def _stall_at(x, a, y, dof, lo=None, hi=None):
    """The rule's inputs at an iterate x: the residual, the (bounded) Gauss-Newton step, its length."""
    r = a @ x - y
    lo = np.full(3, -np.inf) if lo is None else lo
    hi = np.full(3, np.inf) if hi is None else hi
    d = lsq_linear(a, -r, bounds=(lo - x, hi - x), method="bvls").x
    return d, gn.noise_decrement(a, r, d, dof)


def test_the_decrement_is_the_remaining_step_in_joint_standard_errors():
    a, y, x_opt, cov, dof = _problem()
    for k, frac in ((0, 0.05), (1, 0.5), (2, 3.0)):
        x = x_opt.copy()
        x[k] += frac * math.sqrt(cov[k, k])
        d, m = _stall_at(x, a, y, dof)
        assert d == pytest.approx(x_opt - x, abs=1e-9 * se_scale(cov))  # linear: the step back to the optimum
        s2_x = float((a @ x - y) @ (a @ x - y)) / dof  # the residual variance at the iterate
        assert m * m == pytest.approx(d @ (a.T @ a) @ d / s2_x, rel=1e-9)  # d' C^-1 d, C = s2 (A'A)^-1
        assert frac * math.sqrt(1 - 1e-2) <= m * math.sqrt(s2_x / s2_opt(a, y, x_opt, dof))
    assert gn.noise_decrement(a, a @ x_opt - y, np.zeros(3), dof) == 0.0
    assert gn.noise_decrement(a[:, :0], a @ x_opt - y, np.zeros(0), dof) == 0.0


def test_a_stall_at_a_first_order_point_is_accepted_and_one_elsewhere_refused():
    a, y, x_opt, cov, dof = _problem(seed=1)
    se = np.sqrt(np.diag(cov))
    _, m_opt = _stall_at(x_opt, a, y, dof)
    assert gn.first_order_point(1e-9, m_opt)
    _, m_near = _stall_at(x_opt + 0.03 * se, a, y, dof)  # 0.03 standard errors each: within the noise
    assert m_near < gn.FIRST_ORDER_TOL
    assert gn.first_order_point(1e-9, m_near)
    _, m_far = _stall_at(x_opt + np.array([0.0, 0.5, 0.0]) * se, a, y, dof)  # half a standard error off
    assert m_far > gn.FIRST_ORDER_TOL
    assert not gn.first_order_point(1e-9, m_far)
    # a first-order point of the bounded problem: held at a bound its gradient pushes against
    lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
    hi[1] = x_opt[1] - 5 * se[1]
    x_b = x_opt.copy()
    x_b[1] = hi[1]
    x_b[[0, 2]] = lsq_linear(a, y, bounds=(lo, hi), method="bvls").x[[0, 2]]
    d, m_b = _stall_at(x_b, a, y, dof, lo, hi)
    assert abs(d[1]) < 1e-12
    assert gn.first_order_point(1e-9, m_b)
    _, m_free = _stall_at(x_b, a, y, dof)  # the same point without the bound is far from optimal
    assert not gn.first_order_point(1e-9, m_free)
    # the equations out of the linearisation's reach, or no number: refused
    assert not gn.first_order_point(10 * gn.FIRST_ORDER_G_MAX, m_opt)
    assert not gn.first_order_point(float("nan"), m_opt)
    assert not gn.first_order_point(1e-9, float("nan"))


def test_a_buffered_function_reused_gives_each_call_its_own_outputs_and_threads_their_own_buffer():
    # The buffer is made once per thread and reused: a second call with other inputs must not
    # see the first call's inputs, nor overwrite the arrays the first call returned.
    import threading

    import casadi as ca

    from prsa_ctrl.identification.gaussnewton import Buffered

    x, p = ca.SX.sym("x", 2), ca.SX.sym("p")
    e = ca.vertcat(p * x[0] ** 2, ca.sin(x[1]))
    f = ca.Function("f", [x, p], [e]).map("fm", "serial", 3, [1], [])
    b = Buffered(f)
    xa = np.array([[1.0, 2.0, 3.0], [0.1, 0.2, 0.3]])
    xb = np.array([[-4.0, 5.0, 0.5], [1.1, -0.7, 2.0]])
    (ra,) = b(xa, 2.0)
    ra_copy = ra.copy()
    (rb,) = b(xb, -3.0)
    assert np.array_equal(ra, ra_copy)  # the first result is untouched by the second call
    assert np.array_equal(rb.reshape(2, 3, order="F"), np.asarray(f(xb, -3.0)))
    assert np.array_equal(b(xa, 2.0)[0], ra_copy)
    got = {}

    def other(k, xs, pv):
        for _ in range(50):
            got[k] = b(xs, pv)[0]

    ts = [threading.Thread(target=other, args=(k, xs, pv)) for k, (xs, pv) in enumerate(((xa, 2.0), (xb, -3.0)))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert np.array_equal(got[0], ra_copy)
    assert np.array_equal(got[1], rb)


def test_a_full_step_from_where_the_equations_hold_is_taken_within_the_restorable_defect():
    """The rigid solver's rule against creeping along the constraint: from a point whose
    collocation equations hold (largest defect at most CONSTRAINT_TOL) the full Gauss-Newton step
    is taken when it lowers the objective and leaves a defect Newton's steps remove
    (FIRST_ORDER_G_MAX). The numbers are those measured on the ball-screw round trip's refit
    (start 2.1e-12 / 16883.672; full step 1.54e-6 / 12412.517)."""
    assert gn.feasible_full_step(2.1e-12, 1.54e-6, 16883.672, 12412.517)
    # each condition alone refuses it
    assert not gn.feasible_full_step(10 * gn.CONSTRAINT_TOL, 1.54e-6, 16883.672, 12412.517)  # start off the equations
    assert not gn.feasible_full_step(2.1e-12, 10 * gn.FIRST_ORDER_G_MAX, 16883.672, 12412.517)  # a defect too large
    assert not gn.feasible_full_step(2.1e-12, 1.54e-6, 12412.517, 12412.517)  # no objective decrease
    assert not gn.feasible_full_step(2.1e-12, math.nan, 16883.672, 12412.517)
    assert not gn.feasible_full_step(2.1e-12, math.inf, 16883.672, 12412.517)
    # the bounds themselves are inclusive
    assert gn.feasible_full_step(gn.CONSTRAINT_TOL, gn.FIRST_ORDER_G_MAX, 1.0, 0.5)


def test_a_defect_plateau_is_found_on_the_compliant_fits_measured_creep():
    """The rule that takes the full step when the largest collocation defect stays put (rigid and
    compliant fits): the defects measured on the judge's two-mass ball screw's refit after its
    three-iteration warm-up (the window opens at iteration 4) sit on a plateau once five of them
    are within 1 %; the delay search's creep at 1.5 % an iteration is not one yet."""
    refit = [11.6, 0.117, 0.211, 0.00568, 0.0055, 0.00548, 0.00546, 0.00545, 0.00545]
    assert gn.defect_plateau(refit, opened=4)
    assert not gn.defect_plateau(refit[:-1], opened=4)  # one iteration earlier: 0.00568 .. 0.00545, 4 %
    assert not gn.defect_plateau(refit, opened=5)  # the window opens later
    search = [1.91, 0.426, 0.776, 0.0798, 0.0749, 0.0737, 0.0726, 0.0714, 0.0709]
    assert not gn.defect_plateau(search, opened=4)  # falling 1.5 % an iteration
    flat = [0.05] * gn.PLATEAU_ITERATIONS
    assert gn.defect_plateau(flat, opened=0)
    # at or below FIRST_ORDER_G_MAX the stall and first-order rules decide, not this one
    assert not gn.defect_plateau([gn.FIRST_ORDER_G_MAX] * gn.PLATEAU_ITERATIONS, opened=0)
    assert not gn.defect_plateau([0.05] * (gn.PLATEAU_ITERATIONS - 1) + [math.nan], opened=0)
    assert not gn.defect_plateau([0.05] * (gn.PLATEAU_ITERATIONS - 1), opened=0)
    # the ratio bound is inclusive
    assert gn.defect_plateau([0.05 * gn.PLATEAU_RATIO] + [0.05] * (gn.PLATEAU_ITERATIONS - 1), opened=0)
    assert not gn.defect_plateau([0.05 * gn.PLATEAU_RATIO * 1.001] + [0.05] * (gn.PLATEAU_ITERATIONS - 1), opened=0)


@pytest.mark.parametrize("count, chunk", [(10, 4), (8, 4), (3, 1024), (1, 1)])
def test_a_chunked_map_equals_one_map_over_every_interval(count, chunk):
    """gaussnewton.ChunkedMap: the chunks (the last one padded) give exactly the values of one
    serial map over all intervals, every output; a wrong input size is refused."""
    import casadi as ca

    from prsa_ctrl.identification.gaussnewton import ChunkedMap

    x = ca.SX.sym("x", 3)
    p = ca.SX.sym("p", 2)
    y = ca.vertcat(ca.sin(x[0]) * p[0], x[1] * x[2] + p[1], ca.exp(-x[2] ** 2))
    f = ca.Function("f", [x, p], [y, ca.densify(ca.jacobian(y, x))])
    rng = np.random.default_rng(1)
    xs = rng.standard_normal((3, count))
    ps = np.tile([0.7, -1.3], count)
    want = [np.asarray(o).ravel(order="F") for o in f.map(count, "serial")(xs, ps.reshape(count, 2).T)]
    got = ChunkedMap(f, count, chunk=chunk)(xs, ps)
    assert len(got) == 2
    for g, w in zip(got, want):
        assert np.array_equal(g, w)
    with pytest.raises(ValueError, match="expected"):
        ChunkedMap(f, count, chunk=chunk)(xs[:, :-1] if count > 1 else xs[:2], ps)



@pytest.mark.parametrize("count", [1, 5])
def test_a_chunked_map_of_one_chunk_is_the_buffered_map_and_each_thread_has_its_own_buffer(count):
    """gaussnewton.ChunkedMap evaluates through gaussnewton.Buffered: with one chunk its values are
    Buffered's over the map of all intervals, bit for bit; threads calling one ChunkedMap each get
    their own buffer (Buffered's), so neither sees the other's inputs."""
    import threading

    import casadi as ca

    from prsa_ctrl.identification.gaussnewton import Buffered, ChunkedMap

    x = ca.SX.sym("x", 2)
    p = ca.SX.sym("p")
    y = ca.vertcat(p * x[0] ** 2, ca.sin(x[1]))
    f = ca.Function("f", [x, p], [y, ca.densify(ca.jacobian(y, x))])
    rng = np.random.default_rng(2)
    xa, xb = rng.standard_normal((2, count)), rng.standard_normal((2, count))
    ps = np.full(count, 0.7)
    whole = Buffered(f.map(count, "serial"))
    cm = ChunkedMap(f, count, chunk=count)
    for xs in (xa, xb):
        for g, w in zip(cm(xs, ps), whole(xs, ps)):
            assert np.array_equal(g, w)
    want = {0: cm(xa, ps), 1: cm(xb, ps)}
    got = {}

    def other(k, xs):
        for _ in range(50):
            got[k] = cm(xs, ps)

    ts = [threading.Thread(target=other, args=(k, xs)) for k, xs in enumerate((xa, xb))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    for k in (0, 1):
        for g, w in zip(got[k], want[k]):
            assert np.array_equal(g, w)


class _MallInfo2(__import__("ctypes").Structure):
    _fields_ = [(name, __import__("ctypes").c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]


def _mapped_and_heap_of_a_large_array(n=6_000_000):
    """glibc's count of bytes in mapped blocks, and of the heap's free bytes, while a 48 MB array
    (above glibc's largest mapping threshold, 32 MB) is held, and after it is freed."""
    import ctypes

    mallinfo2 = ctypes.CDLL(None).mallinfo2
    mallinfo2.restype = _MallInfo2
    a = np.ones(n)
    held = mallinfo2().hblkhd
    del a
    return held, mallinfo2().fordblks


@pytest.mark.skipif(not hasattr(__import__("ctypes").CDLL(None), "mallinfo2"), reason="the heap policy is glibc's (2.33+)")
def test_a_retained_heap_keeps_large_arrays_in_the_heap_and_gives_the_policy_back():
    # Outside the block glibc maps a 48 MB array on its own and unmaps it when freed (each
    # Gauss-Newton iteration's arrays paged in anew); inside, it is taken from the heap and its
    # memory stays there when freed, for the next; nested blocks keep the policy until the
    # outermost ends; after it, the default again (the memory given back: the next test).
    size = 6_000_000 * 8
    mapped, _ = _mapped_and_heap_of_a_large_array()
    assert mapped >= size
    with gn.retained_heap():
        mapped_in, free_in = _mapped_and_heap_of_a_large_array()
        with gn.retained_heap():
            pass
        mapped_nested, free_nested = _mapped_and_heap_of_a_large_array()
    assert mapped_in < size
    assert free_in >= size
    assert mapped_nested < size
    assert free_nested >= size
    mapped_after, _ = _mapped_and_heap_of_a_large_array()
    assert mapped_after >= size


def _resident_bytes():
    import os

    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not hasattr(__import__("ctypes").CDLL(None), "malloc_trim") or not __import__("os").path.exists(
    "/proc/self/statm"), reason="the heap policy is glibc's; resident memory read from Linux's /proc")
def test_leaving_a_retained_heap_gives_its_free_memory_back():
    # A 48 MB array freed inside the block stays resident in the heap, for the next iteration;
    # leaving the outermost block trims the heap (malloc_trim), so that memory leaves the process.
    # Measured as resident memory, not as glibc's count of free heap bytes: trimming releases the
    # pages of free chunks anywhere in the heap but leaves them counted free (a CI worker that
    # had run other tests held 301 MB 'free' after the trim).
    size = 6_000_000 * 8
    with gn.retained_heap():
        a = np.ones(size // 8)
        del a
        resident_in = _resident_bytes()
    assert resident_in - _resident_bytes() >= 0.9 * size


def test_a_retained_heap_leaves_the_values_and_decorates_a_function():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((300, 300))

    @gn.retained_heap()
    def inverse(m):
        return np.linalg.inv(m)

    assert np.array_equal(inverse(a), np.linalg.inv(a))
