"""Tuner (prsa_ctrl/tuning/tuner.py): the stabilising-set boundary behind the scan (issue 34)."""

from __future__ import annotations

import control
import numpy as np

from prsa_ctrl.tuning.builders import continuous_loop
from prsa_ctrl.tuning.tuner import Tuner


class _BlindTuner(Tuner):
    """A Tuner whose crossover scan misses the stabilising window (only kp < 1 kept: none of
    them stabilises 1/(s - 1))."""

    def _build_scan(self):
        sc = super()._build_scan()
        keep = sc["grid"][:, 0] < 1.0
        return {"grid": sc["grid"][keep], "ms": sc["ms"][keep], "mt": None,
                "stable": sc["stable"][:, keep], "obj": sc["obj"][:, keep]}


def _loop():
    return continuous_loop(control.tf([1.0], [1.0, -1.0]), tf=0.05, horizon=20.0, n_steps=2000, delay=0.2)


def _stable_exact(kp, ki, delay=0.2):
    """Stability of s (s - 1) + (kp s + ki) e^{-L s} by the argument principle (see test_generic)."""
    s = 1j * np.linspace(0.0, 400.0, 80001)
    g = (s * (s - 1.0) + (kp * s + ki) * np.exp(-s * delay)) / (s + 1.0) ** 2
    ph = np.unwrap(np.angle(g))
    return round(-(ph[-1] - ph[0]) / np.pi) == 0


def test_boundary_points_cover_the_stabilising_window():
    tuner = Tuner([_loop()], objective="ie")
    pts = tuner.boundary_points()
    assert pts.shape[1] == 3 and np.all(pts[:, 2] == 0.0)
    small = pts[pts[:, 1] < 0.02]
    stable = [p for p in small if _stable_exact(p[0], p[1])]
    assert stable, "no stabilising point among the boundary points"
    # Independent: the window of kp at small ki is about (1, 7); the points sample it.
    kps = sorted(p[0] for p in stable)
    assert kps[0] < 1.3 and kps[-1] > 4.0


def test_blind_scan_rescued_by_the_boundary():
    """The scan misses every stabilising gain: the D-decomposition points give the tuner its
    start, and the result is that of the full scan (ki within 0.1 %)."""
    lp = _loop()
    blind = _BlindTuner([lp], objective="ie")
    assert not any(lp.stability(g) == "stable" for g in blind.scan_grid)
    res = blind.tune(ms_max=2.0)
    ref = Tuner([_loop()], objective="ie").tune(ms_max=2.0)
    assert res.converged and ref.converged, (res.status, ref.status)
    assert res.ms <= 2.0 and _stable_exact(res.pid.kp, res.pid.ki)
    assert abs(res.pid.ki / ref.pid.ki - 1.0) < 1e-3
