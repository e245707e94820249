"""prsa_ctrl.identification.bidiagonal: the segments' block-bidiagonal collocation equations
solved by block forward substitution equal a sparse direct solve of the assembled matrices."""

import numpy as np
import pytest
from scipy.sparse import lil_matrix
from scipy.sparse.linalg import spsolve

from prsa_ctrl.errors import FitError
from prsa_ctrl.identification.bidiagonal import solve_segments


def _system(lengths, n3=9, nx=3, k=7, seed=0):
    rng = np.random.default_rng(seed)
    M = sum(lengths)
    D = np.eye(n3)[None] + 0.3 * rng.standard_normal((M, n3, n3))
    C = rng.standard_normal((M, n3, nx))
    rhs = rng.standard_normal((M, n3, k))
    first = np.cumsum([0] + list(lengths[:-1]))
    return D, C, rhs, first


@pytest.mark.parametrize("lengths", [[5], [7, 3, 1, 6], [2, 2, 2]])
def test_the_substitution_equals_a_sparse_solve_of_each_segment(lengths):
    n3, nx = 9, 3
    end = slice(n3 - nx, n3)
    D, C, rhs, first = _system(lengths, n3, nx)
    z = solve_segments(D, C, rhs, first, lengths, end)
    for m0, n in zip(first, lengths):  # the segment's matrix, written out
        A = lil_matrix((n * n3, n * n3))
        for m in range(n):
            A[m * n3:(m + 1) * n3, m * n3:(m + 1) * n3] = D[m0 + m]
            if m:
                A[m * n3:(m + 1) * n3, (m - 1) * n3 + n3 - nx:m * n3] = C[m0 + m]
        b = rhs[m0:m0 + n].reshape(n * n3, -1)
        want = spsolve(A.tocsc(), b)
        np.testing.assert_allclose(z[m0:m0 + n].reshape(n * n3, -1), want, rtol=1e-9, atol=1e-9)
        # a segment's first interval never sees the previous segment's end
        assert np.allclose(z[m0], np.linalg.solve(D[m0], rhs[m0]))


def test_a_singular_block_names_its_segment():
    lengths = [4, 5]
    D, C, rhs, first = _system(lengths)
    D[6] = 0.0  # segment 1's third interval
    with pytest.raises(FitError, match="singular in segment 1"):
        solve_segments(D, C, rhs, first, lengths, slice(6, 9))
    D, C, rhs, first = _system(lengths)
    rhs[2, 0, 0] = np.inf
    with pytest.raises(FitError, match="singular in segment 0"):
        solve_segments(D, C, rhs, first, lengths, slice(6, 9))
