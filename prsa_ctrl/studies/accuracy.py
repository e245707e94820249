"""Accuracy against run time of the simulator (read in notebook 04 and measured by
``python benchmarks/bench.py``): a work-precision table of our integrators against scipy's
``solve_ivp`` and python-control's ``input_output_response`` integrating the same equations
(:func:`work_precision`), and each fidelity's error against the most detailed model with its cost
(:func:`fidelity_ladder`). Times are medians of ``repeats`` runs (:func:`timed`).
"""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp

from .._lazy import module
from ..drive.pid import PID
from ..plant.model import plant_model
from ..plant.plantfile import load_plant
from ..sim.integrators import SimSettings, build
from ..sim.engine import run, simulate
from .paper import OMEGA_300_RPM, default_pid

control = module("control")  # python-control, imported when its runs start

__all__ = ["work_precision", "fidelity_ladder", "timed"]


#: Tolerances (rtol = atol, on the scaled states) of every method's runs in the full work-precision table.
TOLERANCES = (1e-4, 1e-6, 3e-7, 1e-7, 3e-8, 1e-8, 1e-10)


class _OverBudget(Exception):
    pass


def timed(fn, repeats: int):
    """Median wall time (s) of ``repeats`` calls of ``fn`` and the last call's result. A call
    that returns ``(False, result)`` did not finish (over budget): it is not repeated."""
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        finished, out = fn()
        times.append(time.perf_counter() - t0)
        if not finished:
            break
    return float(np.median(times)), out, times


def _scene_inputs(fast: bool, tiny: bool = False):
    pre, post = 0.002, (0.005 if tiny else 0.02 if fast else 0.1)
    return OMEGA_300_RPM, [(0.0, 500.0), (pre, 1500.0)], pre + post


def _reference_pid(plant):
    # The tuned design of the paper scene (rounded); fixed so runs are comparable.
    return PID(0.0849, 14.67) if plant.name == "paper-iprsm" else default_pid(plant)



def work_precision(plant=None, fast: bool = False, budget_s: float = 60.0, repeats: int = 3, tiny: bool = False,
                   ab_rounds: int = 0) -> dict:
    """Time (s) and max nut-speed error (rad/s) per method and setting; see module docstring.

    Parameters
    ----------
    plant : Plant, optional
        Default: the paper plant.
    fast : bool
        Short horizon and fewer tolerances.
    budget_s : float, s
        Wall-time budget of one scipy/python-control run (a run over it counts as unfinished).
    repeats : int
        Timed runs per setting; the median is reported.
    tiny : bool
        Every method once at one tolerance (1e-8) on the compliant model over a 7 ms horizon:
        the code paths of a run, not its figures (``benchmarks/bench.py --fast``).
    ab_rounds : int
        After the table, re-run its cheapest prsa-ctrl and scipy rows within 1e-6 rad/s back to
        back this many rounds (``repeats`` runs each per round) in process CPU time: ``"ab_cpu"``
        of the result, each round's ratio and their median, min and max (None when 0 or a side
        has no row within the target).
    """
    plant = plant or load_plant()
    pid = _reference_pid(plant)
    ref_w, load, duration = _scene_inputs(fast, tiny)
    dt = 1e-4
    if isinstance(ab_rounds, bool) or not isinstance(ab_rounds, int) or not 0 <= ab_rounds <= 100:
        raise ValueError(f"ab_rounds = {ab_rounds!r}; expected an integer in [0, 100]")
    grid = np.arange(0.0, duration + 0.5 * dt, dt)

    def ours(fidelity, integ, tol, n=repeats, jit=False):
        s = SimSettings(integrator=integ, rtol=tol, atol=tol, max_steps=200000, jit=jit)

        def once():
            r = simulate(plant, setpoint=ref_w, load=load, duration=duration, controller=pid, fidelity=fidelity,
                         dt=dt, settings=s)
            return True, r

        once()  # builds the integrators (once per setting), not timed
        el, r, _ = timed(once, n)
        return el, np.interp(grid, r.time, r.outputs[0])

    _, w_ref = ours("compliant", "cvodes", 1e-12, 1)
    rows = []

    def record(method, setting, fidelity, elapsed, w, finished=True, **how):
        err = float(np.max(np.abs(w - w_ref))) if finished else math.nan
        rows.append({"method": method, "setting": setting, "fidelity": fidelity, "time_s": elapsed,
                     "max_error_rad_s": err, "finished": finished, **how})

    # One grid for every method, dense around the 1e-6 rad/s target so that each method's cheapest
    # run within it is found to within a factor of about 3 in tolerance.
    tols = (1e-8,) if tiny else (1e-4, 1e-6, 1e-8) if fast else TOLERANCES
    for fidelity in ("compliant",) if tiny else ("rigid", "compliant"):
        for integ in ("cvodes", "idas", "rodas"):
            for jit in (False, True):  # the same integrator on compiled model code (SimSettings.jit)
                for tol in tols:
                    el, w = ours(fidelity, integ, tol, jit=jit)
                    record(f"prsa-ctrl {integ}" + (" jit" if jit else ""), f"tol {tol:g}", fidelity, el, w,
                           run=("ours", integ, tol, jit))

    # The same closed-loop equations for scipy and python-control (scaled states).
    model = plant_model(plant, "compliant")
    built = build(model, False)
    z = ca.SX.sym("z", len(built.scale))
    p = ca.SX.sym("p", 10)  # see simulation._NP; the inputs are constant between steps here
    rhs = ca.Function("rhs", [z, p], [built.rhs(z, p, 0.0)])
    jac = ca.Function("rhs_jacobian", [z, p], [ca.jacobian(built.rhs(z, p, 0.0), z)])
    r0 = simulate(plant, setpoint=ref_w, load=load[0][1], duration=1e-4, controller=pid, fidelity="compliant")
    x0 = np.asarray(r0.states)[:, 0]
    z0 = x0 / built.scale
    bounds = [0.0, load[1][0], duration]

    def params(t0, t1):
        load_t0 = [v for t, v in load if t <= t0 + 1e-12][-1]
        return [ref_w, load_t0, *pid.params, 0.0, t1 - t0, 0.0, 0.0]

    def segment_taus(t0, t1):
        """Normalised output times of one segment: its grid points (the last segment keeps
        its end) plus the end point, from which the next segment restarts."""
        last = t1 == bounds[-1]
        eps = 1e-9 * (t1 - t0)
        pts = grid[(grid >= t0 - eps) & ((grid <= t1 + eps) if last else (grid < t1 - eps))]
        taus = (pts - t0) / (t1 - t0)
        taus = np.minimum(taus, 1.0)
        return (taus if last and taus[-1] >= 1.0 - 1e-9 else np.append(taus, 1.0)), len(pts)

    def scipy_run(method, tol):
        el, w, _ = timed(lambda: _finished(scipy_once(method, tol)), repeats)
        return el, w

    def _finished(w):
        return w is not None, w

    def scipy_once(method, tol):
        t_start = time.perf_counter()
        zc, ws = z0.copy(), []

        def f(tau, zz, pp):
            if time.perf_counter() - t_start > budget_s:
                raise _OverBudget
            return np.asarray(rhs(zz, pp)).ravel()

        try:
            for t0, t1 in zip(bounds[:-1], bounds[1:]):
                pp = params(t0, t1)
                taus, n_pts = segment_taus(t0, t1)
                kw = {"jac": (lambda tau, zz, pp=pp: np.asarray(jac(zz, pp)))} if method != "RK45" else {}
                sol = solve_ivp(f, (0.0, 1.0), zc, method=method, t_eval=taus, rtol=tol, atol=tol, args=(pp,), **kw)
                if not sol.success:
                    raise _OverBudget
                ws.append(sol.y[model.index("omega_nut"), :n_pts] * built.scale[model.index("omega_nut")])
                zc = sol.y[:, -1]
        except _OverBudget:
            return None
        return np.concatenate(ws)

    for method in ("LSODA", "Radau", "BDF"):
        for tol in tols:
            el, w = scipy_run(method, tol)
            record(f"scipy {method}", f"tol {tol:g}", "compliant", el, w if w is not None else w_ref, w is not None,
                   run=("scipy", method, tol))

    def control_run(method, tol):
        el, w, _ = timed(lambda: _finished(control_once(method, tol)), repeats)
        return el, w

    def control_once(method, tol):
        t_start = time.perf_counter()

        def upd(t, zz, u, prm):
            if time.perf_counter() - t_start > budget_s:
                raise _OverBudget
            return np.asarray(rhs(zz, prm["p"])).ravel()

        sys_ = control.nlsys(upd, None, inputs=0, states=len(z0), outputs=len(z0), name="closed_loop")
        zc, ws = z0.copy(), []
        try:
            for t0, t1 in zip(bounds[:-1], bounds[1:]):
                taus, n_pts = segment_taus(t0, t1)
                res = control.input_output_response(
                    sys_, taus, 0, zc, params={"p": params(t0, t1)}, solve_ivp_method=method,
                    solve_ivp_kwargs={"rtol": tol, "atol": tol},
                )
                y = np.asarray(res.states)
                ws.append(y[model.index("omega_nut"), :n_pts] * built.scale[model.index("omega_nut")])
                zc = y[:, -1]
        except (_OverBudget, RuntimeError, ValueError):
            return None
        return np.concatenate(ws)

    for method in ("RK45", "LSODA"):
        for tol in tols[:2] if method == "RK45" else tols:
            el, w = control_run(method, tol)
            record(f"python-control {method}", f"tol {tol:g}", "compliant", el, w if w is not None else w_ref, w is not None)

    def best_time(prefix, target, fidelity="compliant"):
        ok = [r["time_s"] for r in rows if r["method"].startswith(prefix) and r["finished"]
              and r["fidelity"] == fidelity and r["max_error_rad_s"] <= target]
        return min(ok) if ok else math.inf

    target = 1e-6
    ours_t = best_time("prsa-ctrl", target)

    def best_row(prefix):
        ok = [r for r in rows if r["method"].startswith(prefix) and r["finished"] and r["fidelity"] == "compliant"
              and r["max_error_rad_s"] <= target]
        return min(ok, key=lambda r: r["time_s"]) if ok else None

    def cpu_once(how):
        """CPU time (s) of one run of a table row's setting and its error (rad/s)."""
        c0 = time.process_time()
        if how[0] == "ours":
            s = SimSettings(integrator=how[1], rtol=how[2], atol=how[2], max_steps=200000, jit=how[3])
            r = simulate(plant, setpoint=ref_w, load=load, duration=duration, controller=pid, fidelity="compliant",
                         dt=dt, settings=s)
            w = np.interp(grid, r.time, r.outputs[0])
        else:
            w = scipy_once(how[1], how[2])
        return time.process_time() - c0, float(np.max(np.abs(w - w_ref))) if w is not None else math.nan

    ab = None
    pair = best_row("prsa-ctrl"), best_row("scipy")
    if ab_rounds > 0 and all(pair):
        # The two best rows of the table re-run back to back, round by round, in process CPU time (a
        # busy machine stretches wall times; each round's ratio is measured under the same load).
        rounds = []
        for _ in range(ab_rounds):
            times = {}
            for name, row in zip(("prsa-ctrl", "scipy"), pair):
                runs = [cpu_once(row["run"]) for _ in range(max(1, repeats))]
                times[name] = float(np.median([t for t, _ in runs]))
                errs = [e for _, e in runs]
                times[name + " error_rad_s"] = max(errs) if all(map(math.isfinite, errs)) else math.nan
            # a round counts only if both sides stayed within the target (a scipy run over its
            # wall budget returns no trajectory: its error is NaN)
            valid = all(times[k + " error_rad_s"] <= target for k in ("prsa-ctrl", "scipy"))
            times["ratio"] = times["scipy"] / times["prsa-ctrl"] if valid else math.nan
            rounds.append(times)
        ratios = [r["ratio"] for r in rounds if math.isfinite(r["ratio"])] or [math.nan]
        ab = {"prsa-ctrl": f"{pair[0]['method']} {pair[0]['setting']}",
              "scipy": f"{pair[1]['method']} {pair[1]['setting']}",
              "clock": "process CPU time, median of `repeats` runs per round", "rounds": rounds,
              "ratio_median": float(np.median(ratios)), "ratio_min": min(ratios), "ratio_max": max(ratios),
              "rounds_within_target": sum(math.isfinite(r["ratio"]) for r in rounds)}
    return {
        "scene": {"plant": plant.name, "pid": pid.as_dict(), "load": load, "duration_s": duration, "dt_s": dt},
        "rows": rows,
        "target_error_rad_s": target,
        "best_time_s": {
            "prsa-ctrl": ours_t,
            "prsa-ctrl (interpreted, no jit)": min(
                [r["time_s"] for r in rows if r["method"] in ("prsa-ctrl cvodes", "prsa-ctrl idas", "prsa-ctrl rodas")
                 and r["finished"]
                 and r["fidelity"] == "compliant" and r["max_error_rad_s"] <= target] or [math.inf]),
            "prsa-ctrl (SUNDIALS: cvodes, idas)": min(best_time(f"prsa-ctrl {m}", target) for m in ("cvodes", "idas")),
            "scipy": min(best_time(f"scipy {m}", target) for m in ("LSODA", "Radau", "BDF")),
            "python-control": min(best_time(f"python-control {m}", target) for m in ("RK45", "LSODA")),
        },
        "ab_cpu": ab,
        "budget_s": budget_s,
        "repeats": repeats,
    }



def fidelity_ladder(plant=None, fast: bool = False, repeats: int = 3, tiny: bool = False) -> dict:
    """Each fidelity's nut-speed error against the most detailed one (multi-roller with the
    plant's roller tolerances, 1e-10 tolerance) and its cost, on the paper load step with the
    sampled controller (as the tuner verifies).

    Parameters
    ----------
    plant : Plant, optional
    fast : bool
    repeats : int
        Timed runs per setting; the median is reported.
    tiny : bool
        One tolerance (1e-6) per fidelity over a 7 ms horizon (``benchmarks/bench.py --fast``).
    """
    plant = plant or load_plant()
    pid = _reference_pid(plant)
    ref_w, load, duration = _scene_inputs(fast, tiny)
    kw = dict(setpoint=ref_w, load=load, duration=duration, controller=pid, discrete=True)
    ref = run(plant, fidelity="multi-roller", settings=SimSettings(rtol=1e-10, atol=1e-10), **kw)
    w_ref = ref.output("nut_speed")
    drop = float(ref_w - w_ref.min())
    rows = []
    for fidelity in ("rigid", "compliant", "multi-roller"):
        for tol in (1e-6,) if tiny else (1e-4, 1e-6, 1e-8):
            s = SimSettings(rtol=tol, atol=tol)
            run(plant, fidelity=fidelity, settings=s, **kw)  # build once, then time
            el, r, _ = timed(lambda: (True, run(plant, fidelity=fidelity, settings=s, **kw)), repeats)
            err = float(np.max(np.abs(r.output("nut_speed") - w_ref)))
            rows.append({"fidelity": fidelity, "tol": tol, "time_s": el, "max_error_rad_s": err,
                         "error_over_drop": err / drop})
    return {"reference": "multi-roller, tol 1e-10, sampled controller", "peak_drop_rad_s": drop, "rows": rows}
