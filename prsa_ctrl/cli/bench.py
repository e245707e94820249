"""Benchmarks (not tests): run time against error, side by side in one run.

``python -m prsa_ctrl.cli.bench [--out DIR] [--fast]`` (or ``prsa-bench``) writes ``bench.json`` and
``work_precision.png``:

- **work-precision**: wall time against the maximum nut-speed error (rad/s, against a
  1e-12-tolerance CVODES reference) of the closed-loop load step, for our CasADi integrators
  (cvodes, idas) over tolerances and fidelities, and for scipy ``solve_ivp`` (LSODA, Radau, BDF)
  and python-control ``input_output_response`` integrating the *same* model equations
  (the CasADi right-hand side and, for the implicit methods, its exact Jacobian), each
  restarted at the load step like ours;
- **fidelity ladder**: each fidelity's error against the multi-roller model and its cost;
- **tuning**: our tuner against a Kp-Ki grid search whose every point is verified on the
  nonlinear simulator;
- **cold CLI**: ``prsa-tune --load-step 500:1500`` wall time over ``python -c "import control,
  casadi"``;
- **Monte Carlo**: 1000 compliant sampled-loop verifications of the paper scene, serial, 2
  processes and a Dask LocalCluster, in turn (results must agree bit for bit), with the
  integrator the run chose and its measured error, and the serial CPU time per sample;
- **robust tuning**: 16 scenario models against nominal tuning;
- **fit**: ``fit_plant`` on a 4 s, 4 kHz closed-loop record (16001 samples) simulated by the
  toolkit on a perturbed plant (issue 11's run-time figure): wall and CPU time, solver
  iterations and attempts, fitted errors against the truth;
- **targets**: issue 10's speed targets against these medians (``bench.json["targets"]``).

Every time is the median of ``repeats`` runs (default 3; ``--fast``: 1) after a warm-up run,
never the best run; ratios are measured in the same run on the same machine; no target is
asserted here.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["work_precision", "fidelity_ladder", "tuning_benchmark", "cold_cli_benchmark", "monte_carlo_benchmark",
           "robust_tuning_benchmark", "fit_benchmark", "targets", "main"]


class _OverBudget(Exception):
    pass


def _timed(fn, repeats: int):
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


def _scene_inputs(fast: bool):
    from ..studies.paper import OMEGA_300_RPM

    pre, post = 0.002, (0.02 if fast else 0.1)
    return OMEGA_300_RPM, [(0.0, 500.0), (pre, 1500.0)], pre + post


def _reference_pid(plant):
    from ..drive.pid import PID

    # The tuned design of the paper scene (rounded); fixed so runs are comparable.
    return PID(0.0849, 14.67) if plant.name == "paper-iprsm" else __import__("prsa_ctrl.studies.paper", fromlist=["x"]).default_pid(plant)


def work_precision(plant=None, fast: bool = False, budget_s: float = 60.0, repeats: int = 3) -> dict:
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
    """
    import casadi as ca
    import control
    from scipy.integrate import solve_ivp

    from .. import load_plant
    from ..plant.model import plant_model
    from ..sim.simulate import SimSettings, _build, simulate

    plant = plant or load_plant()
    pid = _reference_pid(plant)
    ref_w, load, duration = _scene_inputs(fast)
    dt = 1e-4
    grid = np.arange(0.0, duration + 0.5 * dt, dt)

    def ours(fidelity, integ, tol, n=repeats, jit=False):
        s = SimSettings(integrator=integ, rtol=tol, atol=tol, max_steps=200000, jit=jit)

        def once():
            r = simulate(plant, setpoint=ref_w, load=load, duration=duration, controller=pid, fidelity=fidelity,
                         dt=dt, settings=s)
            return True, r

        once()  # builds the integrators (once per setting), not timed
        el, r, _ = _timed(once, n)
        return el, np.interp(grid, r.time, r.outputs[0])

    _, w_ref = ours("compliant", "cvodes", 1e-12, 1)
    rows = []

    def record(method, setting, fidelity, elapsed, w, finished=True):
        err = float(np.max(np.abs(w - w_ref))) if finished else math.nan
        rows.append({"method": method, "setting": setting, "fidelity": fidelity, "time_s": elapsed,
                     "max_error_rad_s": err, "finished": finished})

    tols = (1e-4, 1e-6, 1e-8) if fast else (1e-4, 1e-6, 1e-8, 1e-10)
    for fidelity in ("rigid", "compliant"):
        for integ in ("cvodes", "idas"):
            for jit in (False, True):  # the same integrator on compiled model code (SimSettings.jit)
                for tol in tols:
                    el, w = ours(fidelity, integ, tol, jit=jit)
                    record(f"prsa-ctrl {integ}" + (" jit" if jit else ""), f"tol {tol:g}", fidelity, el, w)

    # The same closed-loop equations for scipy and python-control (scaled states).
    model = plant_model(plant, "compliant")
    built = _build(model, False)
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
        el, w, _ = _timed(lambda: _finished(scipy_once(method, tol)), repeats)
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
            record(f"scipy {method}", f"tol {tol:g}", "compliant", el, w if w is not None else w_ref, w is not None)

    def control_run(method, tol):
        el, w, _ = _timed(lambda: _finished(control_once(method, tol)), repeats)
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
    return {
        "scene": {"plant": plant.name, "pid": pid.as_dict(), "load": load, "duration_s": duration, "dt_s": dt},
        "rows": rows,
        "target_error_rad_s": target,
        "best_time_s": {
            "prsa-ctrl": ours_t,
            "prsa-ctrl (interpreted, no jit)": min(
                [r["time_s"] for r in rows if r["method"] in ("prsa-ctrl cvodes", "prsa-ctrl idas") and r["finished"]
                 and r["fidelity"] == "compliant" and r["max_error_rad_s"] <= target] or [math.inf]),
            "scipy": min(best_time(f"scipy {m}", target) for m in ("LSODA", "Radau", "BDF")),
            "python-control": min(best_time(f"python-control {m}", target) for m in ("RK45", "LSODA")),
        },
        "budget_s": budget_s,
        "repeats": repeats,
    }


def fidelity_ladder(plant=None, fast: bool = False, repeats: int = 3) -> dict:
    """Each fidelity's nut-speed error against the most detailed one (multi-roller with the
    plant's roller tolerances, 1e-10 tolerance) and its cost, on the paper load step with the
    sampled controller (as the tuner verifies).

    Parameters
    ----------
    plant : Plant, optional
    fast : bool
    repeats : int
        Timed runs per setting; the median is reported.
    """
    from .. import load_plant
    from ..sim.simulate import SimSettings, run

    plant = plant or load_plant()
    pid = _reference_pid(plant)
    ref_w, load, duration = _scene_inputs(fast)
    kw = dict(setpoint=ref_w, load=load, duration=duration, controller=pid, discrete=True)
    ref = run(plant, fidelity="multi-roller", settings=SimSettings(rtol=1e-10, atol=1e-10), **kw)
    w_ref = ref.output("nut_speed")
    drop = float(ref_w - w_ref.min())
    rows = []
    for fidelity in ("rigid", "compliant", "multi-roller"):
        for tol in (1e-4, 1e-6, 1e-8):
            s = SimSettings(rtol=tol, atol=tol)
            run(plant, fidelity=fidelity, settings=s, **kw)  # build once, then time
            el, r, _ = _timed(lambda: (True, run(plant, fidelity=fidelity, settings=s, **kw)), repeats)
            err = float(np.max(np.abs(r.output("nut_speed") - w_ref)))
            rows.append({"fidelity": fidelity, "tol": tol, "time_s": el, "max_error_rad_s": err,
                         "error_over_drop": err / drop})
    return {"reference": "multi-roller, tol 1e-10, sampled controller", "peak_drop_rad_s": drop, "rows": rows}


def tuning_benchmark(plant=None, n_grid: int = 25, fast: bool = False, repeats: int = 3) -> dict:
    """Our tuner (tune + verify the winner) against an n x n Kp-Ki grid with nonlinear
    verification of every point; objective IAE of the paper scene.

    Parameters
    ----------
    plant : Plant, optional
    n_grid : int
        Grid points per gain.
    fast : bool
    repeats : int
        Timed runs of our tuner (median reported). The grid is timed once: it is already the
        sum of ``n_grid**2`` verifications.
    """
    from .. import load_plant
    from ..studies.autotune import Design, actuator_loops, verify
    from ..drive.pid import PID
    from ..studies.scene import load_scene
    from ..tuning.tuner import tune_loops

    plant = plant or load_plant()
    scene = load_scene()
    if fast:
        scene = scene.replace(duration=scene.step_time + 0.05)
        n_grid = min(n_grid, 5)
    def tune_and_verify():
        loops = actuator_loops(plant, scene)
        res = tune_loops(loops, objective=scene.objective, ms_max=scene.ms_max)
        return True, (loops, res, verify(Design("tuned", res.pid, res.margins[0]), plant, scene))

    t_ours, (loops, res, ours), _ = _timed(tune_and_verify, repeats)
    kp0, ki0 = res.pid.kp, res.pid.ki
    kps = kp0 * np.logspace(-0.7, 0.3, n_grid)
    kis = ki0 * np.logspace(-1, 0.5, n_grid)
    t1 = time.perf_counter()
    best = (math.inf, None)
    lp = loops[0]
    verified = 0
    for kp in kps:
        for ki in kis:
            g = (kp, ki, 0.0)
            if not lp.is_stable(g):
                continue  # an unstable loop has nothing to verify
            d = verify(Design("grid", PID(kp, ki), lp.margins(g)), plant, scene)
            verified += 1
            # Every stable point is verified; the best honours the same Ms bound as the tuner.
            if d.margins.ms <= scene.ms_max and d.objective_verified < best[0]:
                best = (d.objective_verified, (kp, ki))
    t_grid = time.perf_counter() - t1
    return {
        "grid": f"{n_grid} x {n_grid}",
        "ours": {"time_s": t_ours, "iae": ours.objective_verified, "kp": kp0, "ki": ki0},
        "grid_search": {"time_s": t_grid, "iae": best[0], "kp_ki": best[1], "points_verified": verified},
        "speedup": t_grid / t_ours,
        "repeats": repeats,
        "ours_no_worse": bool(ours.objective_verified <= best[0] * (1 + 1e-9)),
    }


def monte_carlo_benchmark(n: int = 1000, workers: int = 2, repeats: int = 3,
                          backends=("serial", "process", "dask", "dask-running"), scene: str = "paper-load-step") -> dict:
    """``n`` sampled-loop verifications (the scene's fidelity: compliant for the paper scene) of
    the paper design on the plant's uncertainty samples: serial, ``workers`` processes, a Dask
    LocalCluster started and stopped in each run, and one already running, in turn, median of
    ``repeats``; the backends must agree bit for bit (:func:`prsa_ctrl.studies.montecarlo.benchmark`).

    Parameters
    ----------
    n : int
        Samples per run.
    workers : int
        Processes of the pool and of the LocalCluster.
    repeats : int
        Runs per backend (median reported).
    backends : sequence of str
        Subset of ``("serial", "process", "dask", "dask-running")``; the Dask ones are skipped
        when Dask is missing.
    scene : str
        Scene name or file.
    """
    from ..studies.montecarlo import benchmark
    from ..studies.scene import load_scene

    backends = list(backends)
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        backends = [b for b in backends if not b.startswith("dask")]
    return benchmark(n=n, workers=workers, repeats=repeats, scene=load_scene(scene), backends=backends)


def robust_tuning_benchmark(n_scenarios: int = 16, repeats: int = 3) -> dict:
    """Robust tuning over ``n_scenarios`` scenario models of the robust scene (nominal, the 4
    vertices of its uncertainty box and seeded interior samples) against nominal tuning
    (:func:`prsa_ctrl.tuning.robust.tune_robust_actuator` times both, same machine, same call); the
    median of the per-run ratios over ``repeats`` runs.

    Parameters
    ----------
    n_scenarios : int
        Scenario models in the robust NLP (>= 5).
    repeats : int
    """
    from .. import load_plant
    from ..tuning.robust import scenarios, tune_robust_actuator
    from ..studies.scene import load_scene

    plant, scene = load_plant(), load_scene("robust-load-step")
    scens = scenarios(plant, scene, samples=n_scenarios - 5)
    runs = []
    for _ in range(max(1, repeats)):
        r = tune_robust_actuator(plant, scene, scens=scens)
        runs.append(dict(r.timing_s))
    ratio = [t["tune_robust"] / t["tune_nominal"] for t in runs]
    return {"scenarios": len(scens), "runs_s": runs,
            "median_tune_nominal_s": float(np.median([t["tune_nominal"] for t in runs])),
            "median_tune_robust_s": float(np.median([t["tune_robust"] for t in runs])),
            "median_ratio": float(np.median(ratio)), "ratios": ratio, "repeats": repeats}


#: Issue 11's perturbed plant (inertia -25 %, efficiency 0.88, no-load 0.03 N m, viscous
#: 1.5e-4 N m s/rad, current loop 1200 Hz), the truth of the fit benchmark.
FIT_TRUTH = {"nut.inertia_kg_m2": 1.5e-4, "friction.efficiency": 0.88, "friction.no_load_torque_n_m": 0.03,
             "friction.viscous_n_m_s_per_rad": 1.5e-4, "drive.current_loop_bandwidth_hz": 1200.0}


def fit_record(duration_s: float = 4.0, seed: int = 0):
    """The fit benchmark's record: a closed-loop run of the toolkit's simulator on the plant
    :data:`FIT_TRUTH`, sampled at 4 kHz.

    Multisine speed setpoint 30 +- 20 rad/s (2..150 Hz, 2.5 ms steps), PI speed loop
    (Kp 0.05 N m s/rad, Ki 2 N m/rad), axial load steps every 0.5 s (200, 1500, 300, 2500 N in
    turn), nut angle through the 20-bit encoder with 1e-5 rad of Gaussian interpolation noise
    before quantisation.

    Parameters
    ----------
    duration_s : float, s
        Record length.
    seed : int
        Seed of the multisine phases and of the angle noise.

    Returns
    -------
    (Record, Plant)
        The record and the true plant.
    """
    from .. import PID, load_plant
    from ..identification.data import design_excitation, record_from_arrays
    from ..sim.simulate import run

    truth = load_plant().with_params(FIT_TRUTH)
    t, v = design_excitation("multisine", duration_s=duration_s, sample_time_s=2.5e-3, f_min_hz=2, f_max_hz=150,
                             amplitude=20, offset=30, seed=seed)
    load = [(0.5 * k, (200.0, 1500.0, 300.0, 2500.0)[k % 4]) for k in range(int(math.ceil(duration_s / 0.5)))]
    r = run(truth, setpoint=list(zip(t.tolist(), v.tolist())), load=load, duration=duration_s,
            controller=PID(0.05, 2.0), fidelity="rigid", discrete=True)
    theta = r.states[r.state_labels.index("theta_nut")]
    q = 2 * math.pi / truth.encoder_counts
    noise = 1e-5 * np.random.default_rng(seed).standard_normal(theta.shape)
    angle = np.floor((theta + noise) / q) * q
    rec = record_from_arrays(f"sim-{duration_s:g}s", r.time, r.output("torque_command"), nut_angle_rad=angle,
                             axial_load_n=r.inputs[1])
    return rec, truth


def fit_benchmark(duration_s: float = 4.0, repeats: int = 3) -> dict:
    """Wall and CPU time of :func:`prsa_ctrl.identification.fit.fit_plant` (default keys, default base plant)
    on :func:`fit_record`; medians of ``repeats`` runs after the record is made (the first run
    includes the one-off imports of the solver's SciPy modules).

    Parameters
    ----------
    duration_s : float, s
        Record length (4 s: issue 11's figure, <= 30 s on the reference machine).
    repeats : int
        Timed fits.
    """
    from ..identification.fit import fit_plant

    rec, truth = fit_record(duration_s)
    wall, cpu, res = [], [], None
    for _ in range(max(1, repeats)):
        t0, c0 = time.perf_counter(), time.process_time()
        res = fit_plant([rec])
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    errors = {k: {"fitted": v["value"], "truth": truth.values[k],
                  "relative_error": v["value"] / truth.values[k] - 1,
                  "truth_in_ci95": bool(v["ci95"][0] <= truth.values[k] <= v["ci95"][1])}
              for k, v in res.parameters.items()}
    sv = res.solver
    return {"record": rec.name, "samples": rec.n, "sample_time_s": rec.sample_time_s,
            "median_wall_s": float(np.median(wall)), "median_cpu_s": float(np.median(cpu)),
            "wall_s": wall, "cpu_s": cpu, "iterations": sv["iterations"], "attempts": sv["attempts"],
            "iterations_all_attempts": sv["iterations_all_attempts"], "status": sv["status"],
            "fit_percent": res.fit_percent[rec.name], "parameters": errors, "repeats": repeats}


def targets(result: dict) -> dict:
    """Issue 10's speed targets against the measured medians in ``result`` (those present)."""
    out = {}
    mc = result.get("monte_carlo")
    if mc:
        med = mc["median_s"]
        fastest = min(v for k, v in med.items() if k != "serial") if len(med) > 1 else med["serial"]
        out["monte_carlo_1000_le_20s"] = {"target": 20.0 * mc["n"] / 1000, "measured_s": fastest,
                                          "met": fastest <= 20.0 * mc["n"] / 1000}
        if "parallel_efficiency" in mc:
            eff = mc["parallel_efficiency"]
            out["parallel_efficiency_ge_0.8"] = {"measured": eff, "met": eff >= 0.8}
        if "dask_running_overhead" in mc:
            out["dask_overhead_le_0.15_running_cluster"] = {"measured": mc["dask_running_overhead"],
                                                             "met": mc["dask_running_overhead"] <= 0.15}
        if "dask_overhead" in mc:
            out["dask_overhead_le_0.15_cluster_start_included"] = {"measured": mc["dask_overhead"],
                                                                   "met": mc["dask_overhead"] <= 0.15}
        out["backends_identical"] = {"met": bool(mc["identical"])}
    rb = result.get("robust_tuning")
    if rb:
        out["robust_16_le_5x_nominal"] = {"measured": rb["median_ratio"], "met": rb["median_ratio"] <= 5.0}
    ft = result.get("fit")
    if ft:
        out["fit_4s_le_30s"] = {"target": 30.0, "measured_s": ft["median_wall_s"], "met": ft["median_wall_s"] <= 30.0}
    wp = result.get("work_precision")
    if wp:
        b = wp["best_time_s"]
        ratio = b["scipy"] / b["prsa-ctrl"]
        out["work_precision_ge_30x_scipy"] = {"measured": ratio, "met": ratio >= 30.0,
                                              "without_jit": b["scipy"] / b["prsa-ctrl (interpreted, no jit)"]}
    return out


def cold_cli_benchmark(repeats: int = 3) -> dict:
    """Median cold wall time of the CLI and of importing python-control and CasADi, run in
    turn (A B A B ...) so that drift of the machine's speed hits both.

    Parameters
    ----------
    repeats : int
        Runs of each command.
    """
    def run(cmd):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
        return time.perf_counter() - t0

    imp, cli = [], []
    for _ in range(repeats):
        imp.append(run([sys.executable, "-c", "import control, casadi"]))
        cli.append(run([sys.executable, "-m", "prsa_ctrl.cli.tune", "--load-step", "500:1500", "--quiet"]))
    ratios = [c / i for c, i in zip(cli, imp)]
    return {"import_control_casadi_s": float(np.median(imp)), "prsa_tune_s": float(np.median(cli)),
            "ratio": float(np.median(ratios)), "repeats": repeats}


def _plot(wp: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.0), layout="constrained")
    groups: dict = {}
    for r in wp["rows"]:
        if r["finished"]:
            groups.setdefault(f"{r['method']} ({r['fidelity']})", []).append(r)
    for name, rs in groups.items():
        ax.loglog([r["time_s"] for r in rs], [max(r["max_error_rad_s"], 1e-14) for r in rs], "o-", label=name)
    ax.axhline(wp["target_error_rad_s"], color="k", ls="--", lw=0.8, label="1e-6 rad/s")
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel("max nut-speed error (rad/s)")
    ax.set_title("Work-precision: paper load step, closed loop")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    from ..io.output import write_file

    write_file(path, lambda tmp: fig.savefig(tmp, format="png", dpi=150), flag="--out")  # atomic, as bench.json
    plt.close(fig)


class _UsageError(Exception):
    """Bad input: one line, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        raise _UsageError(" ".join(message.split()))


def main(argv=None) -> int:
    """``prsa-bench``; returns the exit code (0, or 2 with one line for bad input)."""
    try:
        return _main(argv)
    except _UsageError as exc:
        print(f"prsa-bench: error: {exc}", file=sys.stderr)
        return 2


def _check_out(text: str) -> Path:
    """``--out DIR`` checked before any benchmark runs (:func:`prsa_ctrl.io.output.check_directory`:
    a file, a device, a symlink loop, an unwritable place or the package's own folders are
    refused)."""
    from ..io.output import OutputError, check_directory

    try:
        check_directory(text, "--out")
    except OutputError as exc:
        raise _UsageError(str(exc)) from None
    return Path(text)


def _main(argv=None) -> int:
    ap = _Parser(prog="prsa-bench", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench-results", help="folder for bench.json and the figure (created if missing)")
    ap.add_argument("--fast", action="store_true", help="short horizons and a 5 x 5 grid")
    ap.add_argument("--skip", nargs="*", default=[], choices=["work", "fidelity", "tuning", "cli", "montecarlo", "robust", "fit"])
    ap.add_argument("--samples", type=int, default=None, help="Monte-Carlo samples per run (default 1000; 100 with --fast)")
    ap.add_argument("--workers", type=int, default=2, help="processes / Dask workers of the Monte-Carlo benchmark")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per measurement, median reported "
                    "(default 3; 1 with --fast)")
    args = ap.parse_args(argv)
    repeats = args.repeats if args.repeats is not None else (1 if args.fast else 3)
    if not 1 <= repeats <= 20:
        raise _UsageError(f"--repeats {repeats}: expected timed runs per measurement 1..20")
    n_mc = args.samples if args.samples is not None else (100 if args.fast else 1000)
    if not 1 <= n_mc <= 100_000:
        raise _UsageError(f"--samples {n_mc}: expected Monte-Carlo samples 1..100000")
    if not 1 <= args.workers <= 64:
        raise _UsageError(f"--workers {args.workers}: expected 1..64")
    args.out = _check_out(args.out)
    import warnings

    from ..io.output import OutputError, make_directory

    warnings.simplefilter("ignore")
    try:
        make_directory(args.out, "--out")
    except OutputError as exc:
        raise _UsageError(str(exc)) from None
    result: dict = {"machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0],
                                "load_average_1_5_15": list(os.getloadavg()) if hasattr(os, "getloadavg") else None},
                    "repeats": repeats, "statistic": "median"}
    if "work" not in args.skip:
        result["work_precision"] = wp = work_precision(fast=args.fast, budget_s=10.0 if args.fast else 60.0,
                                                    repeats=repeats)
        _plot(wp, args.out / "work_precision.png")
        b = wp["best_time_s"]
        print(f"work-precision at <= 1e-6 rad/s: prsa-ctrl {b['prsa-ctrl']:.3f} s, scipy {b['scipy']:.3f} s "
              f"({b['scipy'] / b['prsa-ctrl']:.1f}x), python-control {b['python-control']:.3f} s "
              f"({b['python-control'] / b['prsa-ctrl']:.1f}x)")
    if "fidelity" not in args.skip:
        result["fidelity_ladder"] = fl = fidelity_ladder(fast=args.fast, repeats=repeats)
        for r in fl["rows"]:
            print(f"fidelity {r['fidelity']:12s} tol {r['tol']:.0e}: {r['time_s']:.3f} s, max error "
                  f"{r['max_error_rad_s']:.2e} rad/s ({100 * r['error_over_drop']:.2f} % of the drop)")
    if "tuning" not in args.skip:
        result["tuning"] = tb = tuning_benchmark(fast=args.fast, repeats=repeats)
        print(f"tuning: ours {tb['ours']['time_s']:.2f} s (IAE {tb['ours']['iae']:.5g}) vs {tb['grid']} grid "
              f"{tb['grid_search']['time_s']:.1f} s (IAE {tb['grid_search']['iae']:.5g}): {tb['speedup']:.0f}x")
    if "montecarlo" not in args.skip:
        result["monte_carlo"] = mc = monte_carlo_benchmark(n=n_mc, workers=args.workers, repeats=repeats)
        med = mc["median_s"]
        print(f"monte carlo ({mc['n']} {mc['fidelity']} verifications, {mc['scene']}): "
              + ", ".join(f"{k} {v:.1f} s" for k, v in med.items())
              + (f"; parallel efficiency {100 * mc['parallel_efficiency']:.0f} %" if "parallel_efficiency" in mc else "")
              + (f"; dask overhead {100 * mc['dask_running_overhead']:+.1f} % on a running cluster"
                 if "dask_running_overhead" in mc else "")
              + (f", {100 * mc['dask_overhead']:+.1f} % with the LocalCluster started and stopped in the run"
                 if "dask_overhead" in mc else "")
              + f"; identical {mc['identical']}"
              + (f"; serial CPU {1e3 * mc['cpu_per_sample_s']:.1f} ms/sample" if "cpu_per_sample_s" in mc else ""))
        ig = mc["integration"]
        print(f"monte carlo integrator: {ig['integrator']}" + (f" (measured error {ig['relative']:.2g} of the "
              f"deviation, accuracy {ig['accuracy']:g}; one-off check {ig['check_s']:.1f} s)" if ig.get("relative")
              is not None else f" ({ig['reason']})") + f"; warm-up (check + compile) {mc['warm_up_s']:.1f} s")
    if "robust" not in args.skip:
        result["robust_tuning"] = rb = robust_tuning_benchmark(repeats=repeats)
        print(f"robust tuning ({rb['scenarios']} scenarios): {rb['median_tune_robust_s']:.2f} s vs nominal "
              f"{rb['median_tune_nominal_s']:.2f} s: ratio {rb['median_ratio']:.1f}x (median of per-run ratios)")
    if "fit" not in args.skip:
        result["fit"] = ft = fit_benchmark(repeats=repeats)
        worst = max(abs(v["relative_error"]) for v in ft["parameters"].values())
        print(f"fit ({ft['samples']} samples, {ft['sample_time_s'] * 1e3:g} ms): wall {ft['median_wall_s']:.1f} s, "
              f"CPU {ft['median_cpu_s']:.1f} s; {ft['iterations']} iterations, {ft['attempts']} attempt(s); "
              f"largest parameter error {100 * worst:.3g} %; truth in every 95 % CI "
              f"{all(v['truth_in_ci95'] for v in ft['parameters'].values())}")
    if "cli" not in args.skip:
        result["cold_cli"] = cb = cold_cli_benchmark(repeats)
        print(f"cold CLI: {cb['prsa_tune_s']:.2f} s vs import control, casadi {cb['import_control_casadi_s']:.2f} s: "
              f"ratio {cb['ratio']:.2f}")
    result["targets"] = tg = targets(result)
    for k, v in tg.items():
        print(f"target {k}: {'met' if v['met'] else 'NOT met'}" + (f" ({v['measured']:.3g})" if "measured" in v else "")
              + (f" ({v['measured_s']:.3g} s)" if "measured_s" in v else ""))
    from .tune import write_json_atomic
    from ..io.output import json_safe

    write_json_atomic(args.out / "bench.json", json_safe(result))
    print(f"results: {args.out / 'bench.json'}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
