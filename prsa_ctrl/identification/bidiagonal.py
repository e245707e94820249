"""The time-domain fit's collocation equations per multiple-shooting segment, solved by block
forward substitution (:mod:`prsa_ctrl.identification.timedomain`, ``_Problem.linearise``).

The linearised collocation equations of one segment are block lower bidiagonal: interval ``m``
has its own square block ``D_m`` (its stage residuals against its stage states) and couples to
the previous interval only through that interval's end state (``C_m``, the residuals against
the interval's start state)::

    D_0 z_0                    = b_0
    D_m z_m + C_m E z_(m-1)    = b_m        (m = 1 .. n - 1)

``E`` picks the end-stage state out of an interval's stage states. The substitution
``z_m = D_m^-1 (b_m - C_m E z_(m-1))`` solves it exactly (the same arithmetic an LU
factorisation of the whole matrix does on this pattern), for every segment at once: the
``D_m`` are inverted together, and step ``m`` advances every segment that has an interval
``m``. Before, a sparse LU per segment and Gauss-Newton iteration (``scipy.sparse.linalg.splu``
with its matrix assembly) took 18 % of the foreign feed axis's rigid three-log fit.
"""

from __future__ import annotations

import numpy as np

from ..errors import FitError

__all__ = ["solve_segments"]


def solve_segments(D, C, rhs, first, lengths, end_rows: slice):
    """Solve every segment's block-bidiagonal collocation equations (module docstring).

    Parameters
    ----------
    D : ndarray, shape (M, n3, n3)
        The diagonal block of each of the ``M`` sample intervals (all segments, in order).
    C : ndarray, shape (M, n3, nx)
        Each interval's residuals against its start state (the previous interval's end state;
        unused for a segment's first interval).
    rhs : ndarray, shape (M, n3, k)
        Right-hand sides, ``k`` columns.
    first, lengths : sequence of int
        Each segment's first interval and its number of intervals.
    end_rows : slice
        The rows of an interval's solution that are its end state (``E``).

    Returns
    -------
    ndarray, shape (M, n3, k)

    Raises
    ------
    FitError
        A diagonal block is singular, or the solution is not finite.
    """
    first = np.asarray(first, int)
    lengths = np.asarray(lengths, int)

    def fail(m: int, why: str) -> FitError:
        g = int(np.searchsorted(first, m, side="right") - 1)
        return FitError(f"collocation equations singular in segment {g}{why}; remedy: shorter segments or a closer "
                        "base plant (--plant)")

    try:
        d_inv = np.linalg.inv(D)
    except np.linalg.LinAlgError as exc:
        det = np.linalg.det(D)
        raise fail(int(np.argmax(~np.isfinite(det) | (det == 0))), f" ({exc})") from None
    z = np.empty_like(rhs)
    with np.errstate(invalid="ignore", over="ignore"):  # (a solution not finite is refused below)
        z[first] = d_inv[first] @ rhs[first]
        for j in range(1, int(lengths.max()) if lengths.size else 0):
            idx_j = first[lengths > j] + j  # step j of every segment that has an interval j
            z[idx_j] = d_inv[idx_j] @ (rhs[idx_j] - C[idx_j] @ z[idx_j - 1][:, end_rows, :])
    finite = np.all(np.isfinite(z), axis=(1, 2))
    if not finite.all():
        raise fail(int(np.argmax(~finite)), "")
    return z
