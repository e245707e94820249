"""The replay of a two-mass linear axis (:mod:`prsa_ctrl.plant.linearaxis`'s model) between two
controller samples, for :func:`prsa_ctrl.identification.axis.simulate_axis`.

Model (load coordinates: m, N), the motor side (the encoder's, mass ``m_m = M - m_l``) with the
axis's friction, the load mass ``m_l`` beyond a spring-damper (``k`` N/m, ``c = 2 zeta sqrt(k m_m
m_l / M)`` N s/m, ``d = x_m - x_l`` its compression)::

    m_m x_m'' = F_drive - k d - c (x_m' - x_l') - F_f(x_m')
    m_l x_l'' = k d + c (x_m' - x_l') + F_load

``F_f`` is the axis's friction (:mod:`prsa_ctrl.identification.axis`: ``Fc+ + Fv+ v`` moving in
+x, ``-Fc- + Fv- v`` in -x, sticking while the net force on the motor side ``F_drive - k d + c
x_l'`` lies in ``[-Fc-, Fc+]``); ``F_load`` the log's external force, on the load mass.

Between two samples the forces are constant (zero-order hold), so each phase (moving in +x,
in -x, stuck) is a linear ODE with a constant input: it is integrated exactly by the matrix
exponential of the phase's augmented system. A phase ends where the motor side's speed reaches
zero (moving) or the net force leaves the stick band (stuck); that instant is found on the exact
solution (regula falsi, Illinois, within a bracket) to ``2^-BISECTION_STEPS`` of the sample (one crossing per sample
and phase is assumed: true while the axial mode is slower than half the sample rate, which a
fit at the controller's rate needs anyway). At most ``MAX_PHASES`` phases per sample (bounded
work; a stick-slip chatter faster than that is cut short and stays in the last phase).
"""

from __future__ import annotations

import math

import numpy as np
from ..drive.sampled import zoh

__all__ = ["TwoMassStepper", "BISECTION_STEPS", "MAX_PHASES"]

#: Halvings of the sample in the search for a phase change (2^-40 of a sample).
BISECTION_STEPS = 40
#: Phases (moving +x, moving -x, stuck) one sample may pass through.
MAX_PHASES = 6


class TwoMassStepper:
    """Exact motion of the two-mass axis over one sample of constant forces.

    Parameters
    ----------
    theta : sequence of float
        ``M`` kg (the whole moving mass), ``Fv+``, ``Fv-`` N s/m, ``Fc+``, ``Fc-`` N.
    load_mass_kg, stiffness_n_per_m, damping_ratio : float
        ``m_l`` (0 < m_l < M), ``k`` (> 0) and ``zeta`` (>= 0) of the spring-damper.
    sample_time_s : float
        The sample (s) the precomputed transitions cover.
    """

    def __init__(self, theta, load_mass_kg: float, stiffness_n_per_m: float, damping_ratio: float,
                 sample_time_s: float):
        m, fvp, fvn, fcp, fcn = (float(a) for a in theta)
        ml, k, zeta = float(load_mass_kg), float(stiffness_n_per_m), float(damping_ratio)
        if not (0.0 < ml < m and k > 0 and zeta >= 0 and all(map(math.isfinite, (ml, k, zeta)))):
            raise ValueError(f"second mass ({ml!r} kg, {k!r} N/m, damping {zeta!r}) of a {m!r} kg axis; expected "
                             "0 < load mass < the axis's mass, stiffness > 0 and damping ratio >= 0, all finite")
        mm = m - ml
        self.m_m, self.m_l, self.k = mm, ml, k
        self.c = 2.0 * zeta * math.sqrt(k * mm * ml / m)
        self.fc = {1: fcp, -1: fcn}
        self.h = float(sample_time_s)
        self._aug = {s: self._augmented(s, fvp if s > 0 else fvn) for s in (1, -1, 0)}
        self._full = {s: zoh(a[:4, :4], a[:4, 4:], self.h) for s, a in self._aug.items()}

    def _augmented(self, s: int, fv: float) -> np.ndarray:
        """Matrix of phase ``s`` over ``[x_m, v_m, d, v_l]`` with the held inputs ``[F_drive, F_load, 1]``
        as three more columns (rows of the inputs: 0)."""
        mm, ml, k, c = self.m_m, self.m_l, self.k, self.c
        a = np.zeros((7, 7))
        if s != 0:
            a[0, 1] = 1.0
            a[1] = [0.0, -(fv + c) / mm, -k / mm, c / mm, 1.0 / mm, 0.0, -s * self.fc[s] / mm]
            a[2, 1], a[2, 3] = 1.0, -1.0
        else:  # the motor side held: x_m and v_m (= 0) constant
            a[2, 3] = -1.0
        a[3] = [0.0, c / ml, k / ml, -c / ml, 0.0, 1.0 / ml, 0.0]
        return a

    def _advance(self, s: int, z: np.ndarray, t: float) -> np.ndarray:
        a = self._aug[s]
        ad, bd = self._full[s] if t == self.h else zoh(a[:4, :4], a[:4, 4:], t)
        return np.concatenate([ad @ z[:4] + bd @ z[4:], z[4:]])

    def net_force(self, z: np.ndarray) -> float:
        """Force on the motor side other than its friction, N (drive, spring, damper)."""
        return float(z[4] - self.k * z[2] - self.c * (z[1] - z[3]))

    def _phase_at_rest(self, z: np.ndarray) -> int:
        f = self.net_force(z)
        return 1 if f > self.fc[1] else (-1 if f < -self.fc[-1] else 0)

    def _ended(self, s: int, z: np.ndarray) -> bool:
        if s == 0:
            return self._phase_at_rest(z) != 0
        return s * z[1] <= 0.0

    def _excess(self, s: int, z: np.ndarray, edge: int) -> float:
        """How far phase ``s`` has ended at ``z`` (> 0 ended, <= 0 not): the speed against the
        direction of motion (m/s), or the net force beyond the stick band's ``edge`` (N)."""
        if s != 0:
            return -s * float(z[1])
        f = self.net_force(z)
        return f - self.fc[1] if edge > 0 else -f - self.fc[-1]

    def _phase_end(self, s: int, z: np.ndarray, left: float, z_end: np.ndarray) -> float:
        """The time (s) at which phase ``s`` started at ``z`` ends within ``left`` (it has ended at
        ``left``, state ``z_end``): bisection until the phase is under way (a start from rest), then
        the Illinois variant of regula falsi on the exact solution, the bracket kept; to
        ``2^-BISECTION_STEPS`` of the sample or ``4 BISECTION_STEPS`` evaluations (bounded)."""
        edge = 0 if s != 0 else self._phase_at_rest(z_end)
        lo, hi = 0.0, left
        g_lo, g_hi = self._excess(s, z, edge), self._excess(s, z_end, edge)
        side = 0
        tol = left * 2.0 ** -BISECTION_STEPS
        for _ in range(4 * BISECTION_STEPS):
            if hi - lo <= tol:
                break
            if g_lo < 0.0 < g_hi:
                mid = hi - g_hi * (hi - lo) / (g_hi - g_lo)
                if not lo < mid < hi:
                    mid = 0.5 * (lo + hi)
            else:  # the start sits on the edge (from rest): halve until the phase is under way
                mid = 0.5 * (lo + hi)
            g = self._excess(s, self._advance(s, z, mid), edge)
            if g > 0.0 or (g == 0.0 and g_lo < 0.0):
                hi, g_hi = mid, g
                if side == 1:
                    g_lo *= 0.5  # Illinois: the stale end's value halved
                side = 1
            else:
                lo, g_lo = mid, g
                if side == -1:
                    g_hi *= 0.5
                side = -1
        return hi

    def step(self, state: tuple[float, float, float, float], f_drive: float, f_load: float):
        """Move from ``state = (x_m m, v_m m/s, d m, v_l m/s)`` over one sample; returns the new state."""
        z = np.array([*state, f_drive, f_load, 1.0])
        left = self.h
        s = 1 if z[1] > 0 else (-1 if z[1] < 0 else self._phase_at_rest(z))
        for _ in range(MAX_PHASES):
            if s == 0:
                z[1] = 0.0
            z1 = self._advance(s, z, left)
            if not self._ended(s, z1):
                z = z1
                break
            hi = self._phase_end(s, z, left, z1)
            z = self._advance(s, z, hi)
            left -= hi
            if s != 0:
                z[1] = 0.0  # the motor side stops: stick or move on
            if left <= 0.0:
                break
            s = self._phase_at_rest(z)
        else:  # MAX_PHASES phase changes in one sample: the rest of it in the last phase
            if s == 0:
                z[1] = 0.0
            z = self._advance(s, z, left)
        return float(z[0]), float(z[1]), float(z[2]), float(z[3])
