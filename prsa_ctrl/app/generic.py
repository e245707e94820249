"""The app's generic tuner (no GUI code): a plant typed as a transfer function of ``s`` and
tuned by :func:`prsa_ctrl.tuning.generic.tune_pid` with its options (objective, PI/PID, Ms/Mt/Mks
bounds, measurement filter order, ideal PID, 2-DOF setpoint weights, an exact delay).

- :func:`parse_transfer_function` reads the typed plant with a small grammar (numbers, ``s``,
  ``+ - * /``, ``^`` or ``**`` with an integer exponent, parentheses, implicit products such as
  ``4s`` or ``(s+1)(s+2)``): no ``eval``, bounded length and nesting;
- :func:`tune_generic` tunes and returns what the page draws (true peaks from the tuner, the
  loop's frequency response from :func:`prsa_ctrl.tuning.builders.continuous_loop`);
- :class:`TuneProcess` runs it in a child process, so that a long tuning (an optimised filter
  with a delay can take minutes) is stopped at once when the user changes an input.

Units are those of the plant: gains in plant-input units per output unit (``kp``), per output
unit and second (``ki``), times seconds (``kd``); times in s; frequencies in rad/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import PlantTextError
from ..options import OBJECTIVES, PEAK_BOUND_RANGE
from ..tuning.plant_text import MAX_DEPTH, MAX_POWER, parse_plant_text, quote_plant_text
from .session import AppInputError, Cancelled, one_line

__all__ = ["parse_transfer_function", "GenericSettings", "GenericView", "tune_generic", "generic_code",
           "TuneProcess", "MAX_TEXT", "MAX_DEPTH", "MAX_POWER"]

#: Longest plant text accepted (characters).
MAX_TEXT = 400


def parse_transfer_function(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator coefficients (highest power of ``s`` first) of a plant typed
    as a rational function of ``s``.

    Parameters
    ----------
    text : str
        E.g. ``"1/(4s+1)"``, ``"2*(s+1)/((s+2)^2*(0.1s+1))"``, ``"(1-0.5s)/(s^2+2s+1)"``: numbers,
        ``s``, ``+ - * /``, ``^`` or ``**`` with a whole exponent up to :data:`MAX_POWER`,
        parentheses nested up to :data:`MAX_DEPTH`; adjacent factors multiply. At most
        :data:`MAX_TEXT` characters. Nothing is evaluated as Python.

    Returns
    -------
    (ndarray, ndarray)
        Numerator and denominator, the denominator's leading coefficient 1 (common factors are
        not cancelled).

    Raises
    ------
    AppInputError
        One line naming the text, where it is wrong, and what is expected.

    Examples
    --------
    >>> num, den = parse_transfer_function("1/(4s+1)")
    >>> num.tolist(), den.tolist()
    ([0.25], [1.0, 0.25])
    """
    try:
        return parse_plant_text(text, max_length=MAX_TEXT, delay_hint="the delay has its own field")
    except PlantTextError as exc:
        shown = quote_plant_text(text) if isinstance(text, str) else repr(text)
        raise AppInputError(f"plant {shown}: {exc}") from None


@dataclass(frozen=True)
class GenericSettings:
    """What the generic panel's controls set (the options of :func:`prsa_ctrl.tuning.generic.tune_pid`).

    Attributes
    ----------
    plant : str
        The plant as typed (:func:`parse_transfer_function`).
    delay_s : float, s
        Exact plant delay (0: none).
    objective : {"ie", "iae", "itae", "ise"}
    controller : {"pi", "pid"}
    ms_max : float
        Bound on the true peak of |S|, in (1, 10).
    mt_max, mks_max : float or None
        Bounds on the true peaks of |T| and of |C F S| (plant-input per output unit), or none.
    filter_order : {0, 1, 2}
        Measurement filter on the whole controller (its time constant optimised).
    ideal : bool
        Ideal PID (no derivative filter).
    setpoint_weights : bool
        Tune the 2-DOF setpoint weights b (and c) after the load design.
    """

    plant: str = "1/(4s+1)"
    delay_s: float = 0.0
    objective: str = "iae"
    controller: str = "pi"
    ms_max: float = 1.4
    mt_max: float | None = None
    mks_max: float | None = None
    filter_order: int = 0
    ideal: bool = False
    setpoint_weights: bool = False

    def kwargs(self) -> dict:
        """The keyword arguments of ``tune_pid`` (checked: one-line :class:`AppInputError`)."""
        if self.objective not in OBJECTIVES:
            raise AppInputError(f"objective {self.objective!r}: expected one of {', '.join(OBJECTIVES)}")
        if self.controller not in ("pi", "pid"):
            raise AppInputError(f"controller {self.controller!r}: expected pi or pid")
        for what, v in (("Ms bound", self.ms_max), ("Mt bound", self.mt_max)):
            if v is not None and not (isinstance(v, (int, float)) and PEAK_BOUND_RANGE[0] < v < PEAK_BOUND_RANGE[1]):
                raise AppInputError(f"{what} {v!r}: expected a number in ({PEAK_BOUND_RANGE[0]:g}, {PEAK_BOUND_RANGE[1]:g})")
        if self.mks_max is not None and not (isinstance(self.mks_max, (int, float)) and math.isfinite(self.mks_max)
                                             and self.mks_max > 0):
            raise AppInputError(f"Mks bound {self.mks_max!r}: expected a positive number")
        if not (isinstance(self.delay_s, (int, float)) and math.isfinite(self.delay_s) and self.delay_s >= 0):
            raise AppInputError(f"delay {self.delay_s!r}: expected a finite number >= 0 in s")
        if self.filter_order not in (0, 1, 2):
            raise AppInputError(f"filter order {self.filter_order!r}: expected 0, 1 or 2")
        return {"objective": self.objective, "controller": self.controller, "ms_max": float(self.ms_max),
                "mt_max": self.mt_max, "mks_max": self.mks_max, "filter_order": int(self.filter_order),
                "ideal": bool(self.ideal), "delay": float(self.delay_s), "setpoint_weights": bool(self.setpoint_weights)}


@dataclass
class GenericView:
    """A generic tuning as the page shows it.

    Attributes
    ----------
    settings : GenericSettings
    num, den : ndarray
        The parsed plant.
    result : TuningResult
        ``tune_pid``'s result (gains, true ``ms``, ``mt``, ``mks``, margins, status, warnings,
        ``filter``, ``setpoint``).
    omega : ndarray, rad/s
        Frequency grid of the loop (the one its true peaks were located on).
    loop : ndarray of complex
        ``L(j omega) = P C F e^{-j omega delay}``.
    noise : ndarray of complex
        ``C F S`` on ``omega`` (the noise sensitivity whose peak is Mks).
    """

    settings: GenericSettings
    num: np.ndarray
    den: np.ndarray
    result: object
    omega: np.ndarray = field(default_factory=lambda: np.zeros(0))
    loop: np.ndarray = field(default_factory=lambda: np.zeros(0, complex))
    noise: np.ndarray = field(default_factory=lambda: np.zeros(0, complex))

    @property
    def gains(self) -> tuple[float, float, float]:
        p = self.result.pid
        return (p.kp, p.ki, p.kd)


def tune_generic(gs: GenericSettings) -> GenericView:
    """Tune the typed plant with ``tune_pid`` and the settings' options; the loop's frequency
    response for the figures comes from the same loop model (``continuous_loop``).

    Raises
    ------
    AppInputError
        Bad settings or a plant ``tune_pid`` refuses (its one-line message).
    """
    import control

    from ..tuning.builders import continuous_loop
    from ..tuning.generic import tune_pid

    kw = gs.kwargs()
    num, den = parse_transfer_function(gs.plant)
    plant = control.tf(num, den)
    try:
        res = tune_pid(plant, **kw)
        filt = res.filter or {}
        lp = continuous_loop(plant, tf=res.pid.tf, horizon=float(res.stats.get("horizon_s") or 1.0), n_steps=50,
                             filter_order=kw["filter_order"], filter_tf=filt.get("tf_s"), ideal=kw["ideal"],
                             delay=kw["delay"])
    except ValueError as exc:
        raise AppInputError(one_line(exc)) from None
    g = lp.gvec((res.pid.kp, res.pid.ki, res.pid.kd))
    pk = lp.peaks(g)
    omega = np.asarray(pk["omega"])
    noise = lp.noise_response(g, omega) if lp.noise is not None else np.zeros(0, complex)
    return GenericView(settings=gs, num=num, den=den, result=res, omega=omega, loop=np.asarray(pk["L"]),
                       noise=np.asarray(noise))


def _poly_text(c: np.ndarray) -> str:
    return "[" + ", ".join(repr(float(x)) for x in c) + "]"


def generic_code(gs: GenericSettings) -> str:
    """The equivalent Python call (``tune_pid`` on ``control.tf``)."""
    num, den = parse_transfer_function(gs.plant)
    kw = gs.kwargs()
    args = ", ".join(f"{k}={v!r}" for k, v in kw.items())
    return "\n".join([
        "import control",
        "from prsa_ctrl.tuning import tune_pid",
        "",
        f"plant = control.tf({_poly_text(num)}, {_poly_text(den)})  # {gs.plant}",
        f"result = tune_pid(plant, {args})",
        "print(result.status, result.pid, result.ms, result.mt, result.mks, result.filter, result.setpoint)",
    ])


# ---- the child process --------------------------------------------------------------------


def _serve(conn) -> None:
    """The child's loop: settings in, ``("ok", view)`` or ``("input"|"error", line)`` out."""
    import warnings

    warnings.simplefilter("ignore")
    while True:
        try:
            gs = conn.recv()
        except (EOFError, OSError):
            return
        try:
            out = ("ok", tune_generic(gs))
        except AppInputError as exc:
            out = ("input", str(exc))
        except Exception as exc:  # noqa: BLE001 - one line in the page, never a traceback
            out = ("error", f"numerical failure: {one_line(exc)}")
        try:
            conn.send(out)
        except (EOFError, OSError):
            return


class TuneProcess:
    """A child process (``spawn``: no fork of the server's threads) that runs
    :func:`tune_generic`; :meth:`run` waits for the answer while polling ``cancelled()``, and a
    cancel ends the child at once (the next :meth:`run` starts a new one). One caller at a time."""

    def __init__(self) -> None:
        self._proc = None
        self._conn = None

    def start(self) -> None:
        """Start the child if none runs (it imports the toolkit: about a second)."""
        import multiprocessing as mp

        if self._proc is not None and self._proc.is_alive():
            return
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child,), daemon=True, name="prsa-app-generic")
        self._proc.start()
        child.close()

    def run(self, gs: GenericSettings, cancelled: Callable[[], bool], poll_s: float = 0.05) -> GenericView:
        """Tune in the child.

        Raises
        ------
        Cancelled
            ``cancelled()`` turned true (the child was ended).
        AppInputError
            Bad settings or plant (one line).
        RuntimeError
            A numerical failure or the child ended (one line).
        """
        self.start()
        self._conn.send(gs)
        while not self._conn.poll(poll_s):
            if cancelled():
                self.stop()
                raise Cancelled("superseded")
            if not self._proc.is_alive():
                self.stop()
                raise RuntimeError("the tuning process ended unexpectedly")
        kind, payload = self._conn.recv()
        if kind == "ok":
            return payload
        if kind == "input":
            raise AppInputError(payload)
        raise RuntimeError(payload)

    def stop(self) -> None:
        """End the child (if any)."""
        if self._proc is not None:
            if self._proc.is_alive():
                self._proc.terminate()
            self._proc.join(timeout=5)
            self._conn.close()
        self._proc = self._conn = None
