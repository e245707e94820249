"""prsa_ctrl.tuning.optimality: the first-order check's non-negative least squares (numpy,
so that the check does not import scipy.optimize) solves the problem SciPy's ``nnls`` solves."""

import numpy as np
import pytest
from scipy.optimize import nnls as scipy_nnls

from prsa_ctrl.tuning.optimality import nnls


def _problems(n_problems, seed):
    rng = np.random.default_rng(seed)
    for _ in range(n_problems):
        m, n = int(rng.integers(1, 9)), int(rng.integers(1, 9))
        a = rng.normal(size=(m, n)) * 10.0 ** rng.uniform(-3, 3, size=n)  # columns of very different size
        kind = rng.integers(0, 4)
        if kind == 1:
            a[:, 0] = a[:, -1]  # a repeated column (rank deficient)
        elif kind == 2:
            a[:, int(rng.integers(0, n))] = 0.0  # a zero column
        b = rng.normal(size=m) if rng.random() < 0.6 else a @ np.abs(rng.normal(size=n))  # consistent b too
        yield a, b


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nnls_agrees_with_scipy_and_meets_its_optimality_conditions(seed):
    for a, b in _problems(400, seed):
        x = nnls(a, b)
        _, r_ref = scipy_nnls(a, b)
        r = np.linalg.norm(a @ x - b)
        scale = max(np.linalg.norm(b), 1e-300)
        assert np.all(x >= 0)
        assert abs(r - r_ref) <= 1e-9 * scale, (a, b, r, r_ref)
        # KKT of min ||a x - b||^2, x >= 0, checked directly: the gradient a'(a x - b) is >= 0
        # everywhere and 0 where x > 0 (each to rounding, per unit column).
        norms = np.linalg.norm(a, axis=0)
        grad = a.T @ (a @ x - b) / np.where(norms > 0, norms, 1.0)
        assert np.all(grad >= -1e-8 * scale)
        assert np.all(np.abs(grad[x > 0]) <= 1e-8 * scale)


def test_nnls_simple_cases():
    # An unconstrained optimum inside the orthant, one on its face, and b = 0.
    a = np.eye(2)
    assert np.allclose(nnls(a, np.array([1.0, 2.0])), [1.0, 2.0])
    assert np.allclose(nnls(a, np.array([1.0, -2.0])), [1.0, 0.0])
    assert np.array_equal(nnls(a, np.zeros(2)), np.zeros(2))
    # The first-order check's shape: gradient columns and a heavy row asking sum(lam) = 1.
    g = np.array([[1.0, -1.0], [0.5, -0.5]])
    a = np.vstack([g, [1e3, 1e3]])
    b = np.array([0.0, 0.0, 1e3])
    x = nnls(a, b)
    assert np.allclose(x, [0.5, 0.5])
    assert np.linalg.norm(g @ x) < 1e-12
