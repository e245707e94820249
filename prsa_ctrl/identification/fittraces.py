"""What a time-domain fit's problem reports besides its solve: each record's share of the
objective, the speed fit % and traces of the segments, and one continuous simulation of a plant
per record (the figures' model trace).

A mixin of the fit's problem (:func:`prsa_ctrl.identification.timedomain.fit_plant`): its
methods read the problem's records, segments, state scales and fidelity (``records``, ``segs``,
``S``, ``fidelity``, ``delay``, ``i_th``, ``_physical``, ``residuals``, ``check``), as the
tuner's mixins read the tuner's (:mod:`prsa_ctrl.tuning.nlp`). Moved out of ``timedomain`` unchanged.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..plant.plantfile import Plant
from .common import fit_percent, symbolic_rhs

__all__ = ["ProblemTraces"]


class ProblemTraces:
    """Objective shares, fit % and simulated traces of a fit's problem (a mixin)."""

    def objective_per_record(self, V, X0, per_segment: bool = False) -> dict:
        """Half the sum of squared weighted residuals of each record's segments (the objective's
        share); ``per_segment``: each record's list of its segments' shares, in time order (the
        delay search's paired test, :func:`prsa_ctrl.identification.delay.segment_test`)."""
        out: dict = {}
        for sg, e in zip(self.segs, self.residuals(V, X0)):
            name = self.records[sg.rec].name
            if per_segment:
                out.setdefault(name, []).append(0.5 * float(e @ e))
            else:
                out[name] = out.get(name, 0.0) + 0.5 * float(e @ e)
        return out

    def simulate(self, sol, plant: Plant) -> dict:
        """One continuous simulation of ``plant`` per record (the figures' model trace).

        From the fitted initial state of the record's first segment to the record's end, with
        the logged command (held over each sample, ``delay`` samples late) and load, through
        the left-out stretches too: no segment joins, so nothing in the trace is a reset of the
        multiple shooting. CVODES (BDF, stiff), one sample per step of a ``mapaccum``.

        Returns
        -------
        dict
            ``{record name: {"time_s", "measured", "model"}}`` (nut speed over each sample
            interval, rad/s, at the interval's end); a record whose simulation fails is left out.
        """
        f, names = symbolic_rhs(plant, (), self.fidelity)
        nx, sc = len(names), self.S
        x = ca.SX.sym("x", nx)
        u = ca.SX.sym("u", 2)
        h = ca.SX.sym("h")
        ode = h * f(x * ca.DM(sc), u, ca.DM.zeros(0)) / ca.DM(sc)
        step = ca.integrator("fit_sim", "cvodes", {"x": x, "p": ca.vertcat(u, h), "ode": ode}, 0.0, 1.0,
                             {"abstol": 1e-9, "reltol": 1e-8, "max_num_steps": 20000})
        _, x0 = self._physical(sol["V"], sol["X0"])
        out = {}
        for r, rec in enumerate(self.records):
            g = next((g for g, sg in enumerate(self.segs) if sg.rec == r), None)
            if g is None or rec.name in out:
                continue
            k0 = self.segs[g].k0
            ks = np.arange(k0, rec.n - 1)
            kd = np.clip(ks - self.delay, 0, None)
            pu = np.vstack([rec.torque_command_n_m[kd], rec.axial_load_n[ks], np.diff(rec.time_s)[ks]])
            try:
                xs = np.asarray(step.mapaccum("fit_sim_acc", len(ks), ["x0"], ["xf"])(
                    x0=x0[:, g] / sc, p=pu)["xf"], float) * sc[:, None]
            except RuntimeError:
                continue
            finally:
                self.check()
            th = np.concatenate([[x0[self.i_th, g]], xs[self.i_th]])
            v = np.diff(th) / np.diff(rec.time_s[k0:])
            if np.all(np.isfinite(v)):
                out[rec.name] = {"time_s": rec.time_s[k0 + 1:], "measured": rec.speed_rad_s[k0:], "model": v}
        return out

    def _fit_percent(self, thetas):
        """Speed fit % per record from the model angles at the samples of each segment."""
        per: dict[str, tuple] = {}
        for sg, th in zip(self.segs, thetas):
            rec = self.records[sg.rec]
            v_model = np.diff(th) / np.diff(rec.time_s[sg.k0:sg.k0 + sg.n + 1])
            v_meas = rec.speed_rad_s[sg.k0:sg.k0 + sg.n]
            m, mm, tt, jj = per.setdefault(rec.name, ([], [], [], []))
            jj.append(sum(len(a) for a in m))
            m.append(v_meas)
            mm.append(v_model)
            tt.append(rec.time_s[sg.k0 + 1:sg.k0 + sg.n + 1])
        out, traces = {}, {}
        for name, (m, mm, tt, jj) in per.items():
            a, b = np.concatenate(m), np.concatenate(mm)
            out[name] = round(fit_percent(a, b), 3)
            # joins: index of each segment's first sample in these arrays (its own initial state)
            traces[name] = {"time_s": np.concatenate(tt), "measured": a, "model": b, "joins": np.array(jj[1:], int)}
        return out, traces
