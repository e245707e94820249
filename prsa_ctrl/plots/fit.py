"""Figures of a fit (:class:`prsa_ctrl.identification.common.FitResult`) and the data they show:
per time-domain record the replay of the plant as written against the measured nut speed (the
replay the validation used, closed loop from the reference or prediction-error, named in the
legend) with the residual below and the record's verdict; per frequency response a Bode overlay
(the data beside the fitted models: the plant as written and, from an FRF fit, the rigid and the
two-mass model), the residual and the coherence when the data carry one; frequency axis in Hz
(or rad/s, ``frequency_unit``).

The figures draw only what the fit computed (``FitResult.traces``, ``solver["validation"]``).
:func:`fit_views` gives the same three views as JSON-ready data (the ``"views"`` section of
``prsa-fit --json``, which the app's calibration panel draws), with, for a time-domain record,
the frequency response of the log itself (:func:`log_response`) beside the written plant's.
"""

from __future__ import annotations

import math
import re
import textwrap
from pathlib import PurePath
from typing import Sequence

import numpy as np

from .._lazy import module
from ..identification.common import FitResult
from ..options import DEFAULT_FREQUENCY_UNIT, FREQUENCY_UNITS

plt = module("matplotlib.pyplot")

__all__ = ["fit_figures", "figure_names", "fit_views", "log_response", "log_traces", "axis_replay_figure",
           "axis_response_figure", "axis_views",
           "VIEW_MAX_POINTS"]

#: Largest number of samples per replay trace in :func:`fit_views` (longer ones are taken at an
#: even stride: every ``k``-th sample, ``k`` stated as ``"every"``).
VIEW_MAX_POINTS = 2000


def _figure_stem(name: str, used: set) -> str:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", PurePath(name).stem) or "data"
    out, i = stem, 2
    while out in used:
        out, i = f"{stem}-{i}", i + 1
    used.add(out)
    return out


def _plain(text) -> str:
    """Text shown as it is in a figure (a ``$`` of a file name starts no mathtext)."""
    return str(text).replace("$", r"\$")


def _unit_factor(unit: str) -> float:
    """Factor from Hz to ``unit`` (:data:`prsa_ctrl.options.FREQUENCY_UNITS`); ValueError naming it otherwise."""
    if unit not in FREQUENCY_UNITS:
        raise ValueError(f"frequency unit {unit!r}; expected one of {', '.join(FREQUENCY_UNITS)}")
    return 2.0 * math.pi * FREQUENCY_UNITS[unit]


def _validation_entry(result: FitResult, name: str) -> tuple[dict | None, str | None]:
    """The validation's metrics of one record (written plant first, else left out) and what they are."""
    v = result.solver.get("validation") or {}
    for part, what in (("written_plant", "plant as written"), ("cross_validation", "left out")):
        e = (v.get(part) or {}).get(name)
        if e is not None and "failed" not in e:
            return e, what
    return None, None


def _verdict_text(e: dict | None) -> str:
    """``explained`` / ``NOT explained`` with the replay error against the noise floor."""
    if e is None:
        return "not validated"
    ratio = e["error_rms_rad_s"] / max(e["noise_floor_rad_s"], 1e-300)
    return (f"{'explained' if e['explained'] else 'NOT explained'} (error {e['error_rms_rad_s']:.3g} rad/s = "
            f"{ratio:.3g} x noise floor)")


def fit_figures(result: FitResult, frequency_unit: str = DEFAULT_FREQUENCY_UNIT, records: Sequence = ()) -> dict:
    """Figures of a fit: per time-domain record the replay of the plant as written against the
    measurement with the residual below; per frequency response a Bode overlay (measured vs
    fitted models, residual, coherence); per record given in ``records`` its own frequency
    response beside the written plant's (:func:`log_traces`).

    Parameters
    ----------
    result : FitResult
    frequency_unit : {"Hz", "rad/s"}
        Unit of the Bode figures' frequency axes (default Hz).
    records : sequence of Record
        The fit's time-domain records (fitted and validation) for their response figures.

    Returns
    -------
    dict
        ``{file stem: matplotlib Figure}`` (``<record>-fit``, ``<response>-bode`` and
        ``<record>-frf``); the caller saves and closes them.
    """
    _unit_factor(frequency_unit)  # before any work
    figs, used, stems = {}, set(), {}
    validation = result.solver.get("validation")
    for name, tr in result.traces.items():
        stem = stems[name] = _figure_stem(name, used)
        if "time_s" in tr:
            t, meas, mod, label, joins = _overlay_data(tr)
            fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 5.5), height_ratios=(2, 1))
            ax1.plot(t, meas, lw=0.8, color="0.5", label="measured (angle difference)")
            ax1.plot(t, mod, lw=1.0, color="C0", label=_plain(label))
            for tj in joins:  # only when the shooting segments themselves are shown
                ax1.axvline(tj, color="C1", lw=0.4, alpha=0.5)
            ax1.set_ylabel("nut speed (rad/s)")
            e, what = _validation_entry(result, name)
            title = f"{name}: {'replay ' if 'simulated' in tr else ''}fit {result.fit_percent.get(name, float('nan')):.1f} %"
            if validation is not None:
                title += f", {_verdict_text(e)}" + (f" ({what})" if what == "left out" else "")
            ax1.set_title(_plain(title), fontsize=10)
            ax1.legend(loc="best", fontsize=8)
            ax2.plot(t, meas - mod, lw=0.6, color="C3")
            ax2.axhline(0.0, color="0.3", lw=0.5)
            ax2.set_ylabel("residual (rad/s)")
            ax2.set_xlabel("time (s)")
            w = (e or {}).get("whiteness")
            if w:
                ax2.set_title(f"residual: autocorrelation lag 1 {w['acf'][1]:+.2f} (white band +/- {w['band']:.2g}), "
                              f"Ljung-Box {'white' if w['white'] else 'not white'}", fontsize=8)
            for ax in (ax1, ax2):
                ax.grid(True, alpha=0.3)
            fig.tight_layout(rect=(0.0, 0.07 if validation is not None else 0.0, 1.0, 1.0))
            if validation is not None:
                _verdict_caption(fig, validation)
            figs[f"{stem}-fit"] = fig
        else:
            figs[f"{stem}-bode"] = _bode_figure(name, tr, result.fit_percent.get(name, float("nan")), frequency_unit,
                                                gain_unit="m/s per N" if getattr(result.plant, "mechanism", None)
                                                == "linear-axis" else "rad/s per N m")
    for name, tr in log_traces(result, records).items():
        figs[f"{stems[name]}-frf"] = _bode_figure(name, {**tr, "title": f"{name}: the log's response (H1 from the "
                                                                        "logged command) beside the written plant's"},
                                                  float("nan"), frequency_unit)
    return figs


def _verdict_caption(fig, validation: dict) -> None:
    """The fit's verdict under the figure (the validation's, wrapped)."""
    text = ("validation: the plant explains the data" if validation["passes"] else
            f"validation: NOT validated; {validation['diagnosis']}" if validation["diagnosis"].startswith("fit failure")
            else f"validation: NOT validated; most likely missing physics: {validation['diagnosis']}")
    fig.text(0.01, 0.005, _plain("\n".join(textwrap.wrap(text, 130)[:3])), fontsize=7, va="bottom",
             color="0.2" if validation["passes"] else "C3")


def _bode_lines(tr: dict) -> list:
    """``[(label, response, is the written model)]`` of a response's trace: the other fitted
    models (rigid, two-mass) first, the plant as written last."""
    models = dict(tr.get("models") or {})
    lines = [(label, np.asarray(g), False) for label, g in models.items() if not label.startswith("plant model")]
    lines.append((tr.get("model_label") or ("fitted plant as written" if models else "fitted model"),
                  np.asarray(tr["model"]), True))
    return lines


def _phase_on(g, pm_deg):
    """Phase of ``g`` (deg) on the branch of ``pm_deg`` (no 360 deg jumps between them)."""
    return np.degrees(np.angle(g * np.exp(-1j * np.radians(pm_deg)))) + pm_deg


def _bode_figure(name: str, tr: dict, fit_pct: float, unit: str = DEFAULT_FREQUENCY_UNIT,
                 gain_unit: str = "rad/s per N m"):
    """Bode overlay of a frequency response: the data (points) beside the fitted models (lines:
    the written plant's and, from an FRF-only fit, the rigid and the two-mass models), frequency
    in ``unit``, the residual of the written model (log magnitude in dB, phase in degrees) and,
    when the data carry one, the coherence below; ``gain_unit`` names the response's unit (a
    linear axis's, in load coordinates: m/s per N)."""
    x = np.asarray(tr["frequency_hz"], float) * _unit_factor(unit)
    gm, gf = np.asarray(tr["measured"]), np.asarray(tr["model"])
    coh = tr.get("coherence")
    n = 4 if coh is not None else 3
    fig, axs = plt.subplots(n, 1, sharex=True, figsize=(8, 7.5 + 1.5 * (n - 3)),
                            height_ratios=(2, 2, 1.3, 1.0)[:n])
    ax1, ax2, ax3 = axs[:3]
    ax1.semilogx(x, 20 * np.log10(np.abs(gm)), ".", ms=4, color="0.4", label="measured")
    pm = np.degrees(np.unwrap(np.angle(gm)))
    ax2.semilogx(x, pm, ".", ms=4, color="0.4")
    for i, (label, g, written) in enumerate(_bode_lines(tr)):
        style = dict(lw=1.4, ls="-") if written else dict(lw=0.9, ls="--")
        ax1.semilogx(x, 20 * np.log10(np.abs(g)), color=f"C{i}", label=_plain(label), **style)
        ax2.semilogx(x, _phase_on(g, pm), color=f"C{i}", **style)
    ax1.set_ylabel(f"|G| (dB re 1 {gain_unit})")  # a linear axis (load coordinates): m/s per N
    chosen = tr.get("chosen")
    ax1.set_title(_plain(tr.get("title") or f"{name}: fit {fit_pct:.1f} %" + (f" (structure: {chosen})" if chosen
                                                                               else "")), fontsize=10)
    ax1.legend(loc="best", fontsize=8)
    ax2.set_ylabel("phase (deg)")
    d = np.log(gm / gf)
    ax3.semilogx(x, 20 / np.log(10) * d.real, ".-", ms=3, lw=0.6, color="C3", label="magnitude (dB)")
    ax3b = ax3.twinx()
    ax3b.semilogx(x, np.degrees(np.angle(np.exp(1j * d.imag))), ".-", ms=3, lw=0.6, color="C4", label="phase (deg)")
    ax3.axhline(0.0, color="0.3", lw=0.5)
    ax3.set_ylabel("residual (dB)", color="C3")
    ax3b.set_ylabel("residual (deg)", color="C4")
    if coh is not None:
        axs[3].semilogx(x, np.asarray(coh, float), ".-", ms=3, lw=0.6, color="C2")
        axs[3].set_ylim(0.0, 1.05)
        axs[3].set_ylabel("coherence")
    axs[-1].set_xlabel(f"frequency ({unit})")
    for ax in axs:
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return fig


def _overlay_data(tr: dict):
    """What a record's overlay figure plots: ``(time_s, measured, model, model label, join
    times)``. The model is the continuous replay of the plant as written when there is one
    (the validation's, :mod:`prsa_ctrl.identification.validation`, labelled with its mode: no
    segment joins, so no resets that look like model error);
    otherwise the shooting segments, each drawn apart (NaN between them) with its start marked.
    Gaps in the data (left-out stretches) are broken with NaN too."""
    sim = tr.get("simulated")
    if sim is not None:
        t, meas, mod = (np.asarray(sim[k], float) for k in ("time_s", "measured", "model"))
        breaks, joins = np.zeros(0, int), []
        label = sim.get("label", "fitted plant, one continuous simulation")
    else:
        t, meas, mod = (np.asarray(tr[k], float) for k in ("time_s", "measured", "model"))
        breaks = np.asarray(tr.get("joins", np.zeros(0, int)), int)
        joins = [float(t[j]) for j in breaks]
        label = "fitted model (shooting segments; each starts at a marked join)"
    gap = np.flatnonzero(np.diff(t) > 1.5 * float(np.median(np.diff(t))))
    cut = np.union1d(gap + 1, breaks)
    return (*(np.insert(a, cut, np.nan) for a in (t, meas, mod)), label, joins)


def axis_replay_figure(replay):
    """The overlay figure of a linear-axis log's replay
    (:class:`~prsa_ctrl.identification.axis.AxisReplay`): position error (or position), velocity
    and force, measured against the replay of the plant (closed loop from the reference when the
    log describes its controller, else open loop from the logged command: the legend and the
    title say which), and the velocity residual (measured - replayed) below."""
    fig, ax = plt.subplots(4, 1, sharex=True, figsize=(9, 8.5), height_ratios=(1, 1, 1, 0.8))
    t = np.asarray(replay.time_s, float)
    how = "closed-loop replay from the reference" if replay.closed_loop else "open-loop replay from the logged command"
    base, what = ((replay.reference_m, "position error (reference - position), um") if replay.reference_m is not None
                  else (np.mean(replay.position_measured), "position - mean, um"))
    pairs = ((1e6 * (base - replay.position_measured), 1e6 * (base - replay.position_simulated), what),
             (replay.velocity_measured, replay.velocity_simulated, "velocity, m/s"),
             (replay.force_measured, replay.force_simulated, "force, N"))
    for a, (meas, sim, label) in zip(ax, pairs):
        a.plot(t, meas, label="measured")
        a.plot(t, sim, "--", label=how)
        a.set_ylabel(label)
    vr = np.asarray(replay.velocity_measured, float) - np.asarray(replay.velocity_simulated, float)
    ax[3].plot(t, vr, lw=0.6, color="C3")
    ax[3].axhline(0.0, color="0.3", lw=0.5)
    ax[3].set_ylabel("velocity residual, m/s")
    ax[3].set_xlabel("time, s")
    e = replay.errors_percent
    fig.suptitle(_plain(f"{PurePath(replay.name).name} ({how}): errors position {e['position']:.3g} %, velocity "
                        f"{e['velocity']:.3g} %, force {e['force']:.3g} %"), fontsize=10)
    for a in ax:
        a.grid(True, alpha=0.3)
    for a in ax[:3]:
        a.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return fig


def figure_names(names: Sequence[str], frf_names: Sequence[str] = (), log_responses: bool = False) -> list[str]:
    """File stems :func:`fit_figures` will use for these record and response names (in order:
    fitted and validation records, then responses; with ``log_responses`` each record's
    ``-frf`` too, as ``fit_figures(..., records=...)`` draws them), so output paths can be
    checked first."""
    used: set = set()
    stems = [_figure_stem(n, used) for n in names]
    return ([f"{s}-fit" for s in stems] + [f"{_figure_stem(n, used)}-bode" for n in frf_names]
            + ([f"{s}-frf" for s in stems] if log_responses else []))


# ---- the views as data (prsa-fit --json "views", the app's calibration panel) -------------------


#: What :func:`log_response` estimates (the label of its data in the views).
LOG_RESPONSE_TEXT = ("H1 estimate torque command -> nut speed from the log (Welch, Hann, 50 % overlap): open-loop "
                     "estimator, biased where the speed loop feeds noise or unlogged disturbances (load changes) "
                     "back into the command; the coherence says where")


def log_response(record, nperseg: int | None = None, power_floor: float = 1e-3):
    """Frequency response torque command -> nut speed of a time-domain log, with its coherence.

    The H1 estimate ``S_uy / S_uu`` of the logged command ``u`` and the one-sample angle
    difference ``y`` (Welch: Hann window, 50 % overlap, linear detrend), over the bins from the
    second one up to ``0.45 / Ts`` whose command power is above ``power_floor`` times the
    largest. An open-loop estimator: where the speed loop feeds measurement noise or a
    disturbance the log does not hold back into the command, it is biased, and the coherence
    is low there.

    Parameters
    ----------
    record : Record
    nperseg : int, optional
        Samples per Welch segment (default: the power of two at or below half the log, 256..4096: three
        segments or more).
    power_floor : float
        Relative command power below which a bin counts as not excited and is not shown (as
        :func:`prsa_ctrl.identification.data.frf_from_record`).

    Returns
    -------
    (frequency_hz, response, coherence) : ndarrays (Hz, (rad/s)/(N m) complex, 0..1), or None
        for a log too short (under 256 samples) or without command power.
    """
    # the command of sample k beside the speed (angle_k - angle_k-1) / Ts (sample 0 has none): the
    # pairing of the sampled model response (command held over a sample, backward difference)
    out = _h1([(np.asarray(record.torque_command_n_m, float)[1:], np.asarray(record.speed_rad_s, float))],
              float(record.sample_time_s), nperseg, power_floor)
    return None if out is None else (out[0], out[1][0], out[2][0])


def _h1(pairs, ts: float, nperseg: int | None, power_floor: float):
    """H1 estimates ``S_uy / S_uu`` and coherences of the input/output ``pairs`` (Welch as
    :func:`log_response`) on the bins the first pair's input excites; None when it excites none
    (or a log is under 256 samples or not finite)."""
    from scipy.signal import csd, welch

    u, y = pairs[0]
    n = len(u)
    if n < 256 or not all(np.all(np.isfinite(a)) for pr in pairs for a in pr):
        return None
    if nperseg is None:
        nperseg = int(min(4096, max(256, 2 ** int(math.floor(math.log2(max(n // 2, 1)))))))
    nperseg = int(min(nperseg, n))
    kw = dict(fs=1.0 / ts, window="hann", nperseg=nperseg, noverlap=nperseg // 2, detrend="linear")
    spectra = [(welch(a, **kw)[1], welch(b, **kw)[1], csd(a, b, **kw)[1]) for a, b in pairs]
    f = welch(u, **kw)[0]
    p_uu, p_yy, _ = spectra[0]
    top = float(np.max(p_uu[1:])) if len(p_uu) > 1 else 0.0
    if not top > 0:
        return None
    keep = (np.arange(len(f)) >= 2) & (f <= 0.45 / ts) & (p_uu > power_floor * top)
    for q_uu, q_yy, _ in spectra:
        keep &= (q_uu > 0) & (q_yy > 0)
    if np.count_nonzero(keep) < 2:
        return None
    gs = [q_uy[keep] / q_uu[keep] for q_uu, _, q_uy in spectra]
    cohs = [np.clip(np.abs(q_uy[keep]) ** 2 / (q_uu[keep] * q_yy[keep]), 0.0, 1.0) for q_uu, q_yy, q_uy in spectra]
    ok = np.logical_and.reduce([np.isfinite(g) & (g != 0) for g in gs])
    if np.count_nonzero(ok) < 2:
        return None
    return f[keep][ok], [g[ok] for g in gs], [c[ok] for c in cohs]


def axis_response_figure(replay, nperseg: int | None = None):
    """The frequency response of a linear-axis log beside its replay's
    (:class:`~prsa_ctrl.identification.axis.AxisReplay`), on a Hz axis: force -> velocity (m/s
    per N), the H1 estimate of the measured force and velocity beside the same estimate of the
    replayed ones (one estimator, the bins the measured force excites; in a closed loop it is
    not the plant's own response, but data and replay pass through the same loop), the residual
    ``data / replay`` in dB and degrees, and the data's coherence. None for a log under 256
    samples or without force power."""
    ts = float(np.median(np.diff(np.asarray(replay.time_s, float))))
    out = _h1([(np.asarray(replay.force_measured, float), np.asarray(replay.velocity_measured, float)),
               (np.asarray(replay.force_simulated, float), np.asarray(replay.velocity_simulated, float))],
              ts, nperseg, 1e-3)
    if out is None:
        return None
    f, (gm, gs), (coh, _) = out
    how = "closed-loop replay" if replay.closed_loop else "open-loop replay"
    fig, ax = plt.subplots(4, 1, sharex=True, figsize=(9, 8.5), height_ratios=(1.2, 1, 0.8, 0.6))
    ax[0].semilogx(f, 20 * np.log10(np.abs(gm)), ".", ms=3, label="data (H1 of the log)")
    ax[0].semilogx(f, 20 * np.log10(np.abs(gs)), "-", label=f"{how} (same estimator)")
    ax[0].set_ylabel("|G| (dB re 1 m/s per N)")
    ax[0].legend(loc="lower left", fontsize=8)
    ax[1].semilogx(f, np.degrees(np.unwrap(np.angle(gm))), ".", ms=3)
    ax[1].semilogx(f, np.degrees(np.unwrap(np.angle(gs))), "-")
    ax[1].set_ylabel("phase (deg)")
    d = np.log(gm / gs)
    ax[2].semilogx(f, 20 / np.log(10) * d.real, color="C3", label="magnitude (dB)")
    ax[2].semilogx(f, np.degrees(d.imag), color="C4", label="phase (deg)")
    ax[2].axhline(0.0, color="0.3", lw=0.5)
    ax[2].set_ylabel("residual data/replay")
    ax[2].legend(loc="upper left", fontsize=8)
    ax[3].semilogx(f, coh, color="C2")
    ax[3].set_ylim(0.0, 1.05)
    ax[3].set_ylabel("coherence")
    ax[3].set_xlabel("frequency (Hz)")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    fig.suptitle(_plain(f"{PurePath(replay.name).name}: force -> velocity, data beside the {how}"), fontsize=10)
    fig.tight_layout()
    return fig


def _floats(a) -> list:
    """A float array as a JSON list (NaN and infinities as None: no NaN reaches a reader)."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(a, float)]


def _bode_data(g, pm_deg=None) -> dict:
    g = np.asarray(g, complex)
    ph = np.degrees(np.unwrap(np.angle(g))) if pm_deg is None else _phase_on(g, pm_deg)
    return {"magnitude_db": _floats(20 * np.log10(np.abs(g))), "phase_deg": _floats(ph)}


def _frf_view(f_hz, gm, lines, coherence, source: str, chosen=None, fit_percent=None) -> dict:
    """One frequency-response view: the data's magnitude and phase, each model's, the written
    model's residual, the coherence. Phases are drawn on the branch of the written model's
    unwrapped phase (a smooth curve: unwrapping noisy data bins would pile up turns), the data
    within half a turn of it."""
    gm = np.asarray(gm, complex)
    written = np.asarray(next(g for _, g, w in lines if w), complex)
    ref = np.degrees(np.unwrap(np.angle(written)))
    pm = _phase_on(gm, ref)
    d = np.log(gm / written)
    return {
        "source": source,
        "frequency_hz": _floats(f_hz),
        "measured": {"magnitude_db": _floats(20 * np.log10(np.abs(gm))), "phase_deg": _floats(pm)},
        "models": {label: {**_bode_data(g, ref), "written": bool(w)} for label, g, w in lines},
        "residual": {"magnitude_db": _floats(20 / np.log(10) * d.real),
                     "phase_deg": _floats(np.degrees(np.angle(np.exp(1j * d.imag))))},
        "coherence": None if coherence is None else _floats(coherence),
        "chosen": chosen,
        "fit_percent": None if fit_percent is None or not math.isfinite(fit_percent) else float(fit_percent),
    }


def log_traces(result: FitResult, records: Sequence = ()) -> dict:
    """Each time-domain record's own frequency response (:func:`log_response`) beside the
    written plant's: ``{record name: {"frequency_hz", "measured", "model" (complex,
    (rad/s)/(N m)), "coherence", "model_label"}}``. The model is ``result.plant`` linearised at
    the record's mean speed and load, sampled at its sample time, with the fit's command shift
    (logged command -> action, ``solver["command_delay"]``); a record too short for a spectral
    estimate, or whose model response cannot be evaluated, has none."""
    from ..identification.frf import frf_response

    out: dict = {}
    if result.plant is None:
        return out
    cd = result.solver.get("command_delay") or {}
    shift = int(cd.get("shift_samples", result.plant.command_delay_samples))
    fidelity = result.solver.get("fidelity", "rigid")
    for rec in records:
        if rec.name in out or rec.name not in result.traces:
            continue
        est = log_response(rec)
        if est is None:
            continue
        f, g, coh = est
        speed = float(np.mean(rec.speed_rad_s))
        load = float(np.mean(rec.axial_load_n)) if rec.axial_load_n is not None else 0.0
        try:
            model = frf_response(result.plant, f, speed_rad_s=speed, load_n=load, sample_time_s=rec.sample_time_s,
                                 delay_samples=shift, fidelity=fidelity if load else "rigid")
        except (ValueError, RuntimeError, np.linalg.LinAlgError):
            continue
        if np.all(np.isfinite(model)) and np.all(model != 0):
            out[rec.name] = {"frequency_hz": f, "measured": g, "model": model, "coherence": coh,
                             "model_label": f"plant as written (linearised at {speed:.3g} rad/s, {load:.4g} N)"}
    return out


def fit_views(result: FitResult, records: Sequence = (), max_points: int = VIEW_MAX_POINTS) -> dict:
    """The fit's three views as JSON-ready data: the replay of each record, the frequency
    responses (data beside the fitted models, Hz) and the residuals, with the verdict.

    Parameters
    ----------
    result : FitResult
        A fit (:func:`~prsa_ctrl.identification.timedomain.fit_plant`,
        :func:`~prsa_ctrl.identification.frfplant.fit_frf_structure`, ...).
    records : sequence of Record
        The time-domain records of the fit (fitted and validation): each one's frequency
        response (:func:`log_response`) is shown beside the written plant's, linearised at the
        record's mean speed and load, sampled at its sample time and delayed by the fit's
        command shift (logged command -> action).
    max_points : int
        Largest number of samples per replay trace (longer ones at an even stride).

    Returns
    -------
    dict
        ``verdict``: ``{"validated": bool or None (no validation ran), "diagnosis", "reasons",
        "replay" (how the records were replayed)}``;
        ``replay``: per record ``{"label" (which replay), "mode" (``"closed-loop"``,
        ``"prediction-error"`` or ``"shooting segments"``), "every", "time_s",
        "measured_rad_s", "model_rad_s", "residual_rad_s", "fit_percent", "explained",
        "error_rms_rad_s", "noise_floor_rad_s", "whiteness"}``;
        ``frf``: per response ``{"source", "frequency_hz", "measured": {"magnitude_db",
        "phase_deg"}, "models": {label: {"magnitude_db", "phase_deg", "written"}}, "residual":
        {"magnitude_db", "phase_deg"}, "coherence" (or None), "chosen", "fit_percent"}`` (None for a
        log's response: the verdict is the replay's). Every number finite or None.
    """
    if not (isinstance(max_points, int) and max_points >= 2):
        raise ValueError(f"max_points = {max_points!r}; expected an integer >= 2")
    validation = result.solver.get("validation")
    verdict = {"validated": None if validation is None else bool(validation["passes"]),
               "diagnosis": None if validation is None else validation.get("diagnosis"),
               "reasons": [] if validation is None else list(validation.get("reasons") or []),
               "replay": None if validation is None else validation.get("replay")}
    replay, frf = {}, {}
    for name, tr in result.traces.items():
        if "time_s" in tr:
            sim = tr.get("simulated")
            src = sim if sim is not None else tr
            t, meas, mod = (np.asarray(src[k], float) for k in ("time_s", "measured", "model"))
            every = max(1, math.ceil(len(t) / max_points))
            idx = np.arange(0, len(t), every)
            label = (sim.get("label", "fitted plant, one continuous simulation") if sim is not None else
                     "fitted model (shooting segments, each from the measured state)")
            mode = ("shooting segments" if sim is None else "closed-loop" if "closed-loop" in label else
                    "prediction-error")
            e, _ = _validation_entry(result, name)
            pct = result.fit_percent.get(name)
            replay[name] = {
                "label": label, "mode": mode, "every": every,
                "time_s": _floats(t[idx]), "measured_rad_s": _floats(meas[idx]), "model_rad_s": _floats(mod[idx]),
                "residual_rad_s": _floats((meas - mod)[idx]),
                "fit_percent": None if pct is None or not math.isfinite(pct) else float(pct),
                "explained": None if e is None else bool(e["explained"]),
                "error_rms_rad_s": None if e is None else e["error_rms_rad_s"],
                "noise_floor_rad_s": None if e is None else e["noise_floor_rad_s"],
                "whiteness": None if e is None else e.get("whiteness"),
            }
        else:
            coh = tr.get("coherence")
            frf[name] = _frf_view(tr["frequency_hz"], tr["measured"], _bode_lines(tr), coh,
                                  "frequency response given to the fit", tr.get("chosen"),
                                  result.fit_percent.get(name))
    for name, tr in log_traces(result, records).items():
        if name not in frf:
            # no fit % here: the verdict is the replay's; this estimate is biased where the
            # coherence is low, and a fit % over a band depends on the band's own spread
            frf[name] = _frf_view(tr["frequency_hz"], tr["measured"], [(tr["model_label"], tr["model"], True)],
                                  tr["coherence"], LOG_RESPONSE_TEXT)
    return {"verdict": verdict, "replay": replay, "frf": frf}


def axis_views(result, max_points: int = VIEW_MAX_POINTS) -> dict:
    """A linear-axis fit's three views as JSON-ready data, in :func:`fit_views`'s layout (the
    app's calibration panel draws them): what ``prsa-fit LOG --log-format F --plots DIR`` draws
    (:func:`axis_replay_figure`, :func:`axis_response_figure`), from the same replays.

    ``result`` is an :class:`~prsa_ctrl.identification.axis.AxisFit` or a
    :class:`~prsa_ctrl.identification.axiscompliant.TwoMassAxisFit` (its ``replays``, and the
    two-mass fit's ``validation`` as the verdict). Per log: ``replay`` the measured speed beside
    the plant's replay (closed loop from the reference when the log describes its controller) and
    the residual, ``*_rad_s`` keys holding m/s (``"unit": "m/s"``, load coordinates); ``frf`` the
    force -> speed response of the log (H1) beside the replay's through the same estimator (one
    estimator, the bins the measured force excites, a Hz axis), its residual and the coherence.
    Every number finite or None.
    """
    if not (isinstance(max_points, int) and max_points >= 2):
        raise ValueError(f"max_points = {max_points!r}; expected an integer >= 2")
    validation = getattr(result, "validation", None) or None
    written = (validation or {}).get("written_plant", {})
    verdict = {"validated": None if validation is None else bool(validation["passes"]),
               "diagnosis": None if validation is None else validation.get("diagnosis"),
               "reasons": [] if validation is None else list(validation.get("reasons") or []),
               "replay": None if validation is None else validation.get("replay")}
    replay, frf = {}, {}
    for r in result.replays:
        name = PurePath(r.name).name
        how = "closed-loop replay from the reference" if r.closed_loop else "open-loop replay from the logged command"
        t = np.asarray(r.time_s, float)
        meas, mod = np.asarray(r.velocity_measured, float), np.asarray(r.velocity_simulated, float)
        every = max(1, math.ceil(len(t) / max_points))
        idx = np.arange(0, len(t), every)
        e = written.get(r.name)
        pct = r.fit_percent.get("velocity")
        replay[name] = {"label": f"plant as written, {how}", "mode": "closed-loop" if r.closed_loop else "open-loop",
                        "every": every, "unit": "m/s", "time_s": _floats(t[idx]), "measured_rad_s": _floats(meas[idx]),
                        "model_rad_s": _floats(mod[idx]), "residual_rad_s": _floats((meas - mod)[idx]),
                        "fit_percent": None if pct is None or not math.isfinite(pct) else float(pct),
                        "explained": None if e is None else bool(e["explained"]),
                        "error_rms_rad_s": None if e is None else e["error_rms_m_s"],
                        "noise_floor_rad_s": None if e is None else e["noise_floor_m_s"], "whiteness": None}
        ts = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        out = _h1([(np.asarray(r.force_measured, float), meas), (np.asarray(r.force_simulated, float), mod)],
                  ts, None, 1e-3) if ts > 0 else None
        if out is not None:
            f, (gm, gs), (coh, _) = out
            view = _frf_view(f, gm, [(f"{how} (same estimator)", gs, True)], coh,
                             "H1 estimate force -> speed of the log (Welch, Hann, 50 % overlap) beside the same "
                             "estimate of the replay: in a closed loop not the plant's own response, but data and "
                             "replay pass through the same loop")
            frf[name] = {**view, "unit": "(m/s)/N"}
    return {"verdict": verdict, "replay": replay, "frf": frf, "unit": "m/s"}
