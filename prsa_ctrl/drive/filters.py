"""Speed-measurement and torque-command filters of the drive, continuous and discretised.

Every filter is a small frozen dataclass holding its physical parameters (Hz, dimensionless
damping, dB) with a continuous transfer function of at most second order,

``H(s) = (n2 s^2 + n1 s + n0) / (d2 s^2 + d1 s + d0)``  (unit DC gain),

and its discretisation at a drive sample time ``ts`` as one normalised biquad
(:class:`DiscreteBiquad`, ``a0 = 1``),

``y[k] = b0 x[k] + b1 x[k-1] + b2 x[k-2] - a1 y[k-1] - a2 y[k-2]``,

which is what a drive's filter block takes. Three discretisations (:meth:`Filter.biquad`):

``"tustin"``
    ``s = K (z - 1)/(z + 1)`` with ``K = 2/ts``, or with ``prewarp=True``
    ``K = w0 / tan(w0 ts / 2)`` at the filter's characteristic frequency ``w0`` (corner or
    centre, rad/s), so the discrete filter has its corner/notch exactly at ``w0``. Same as
    python-control's ``sample_system(H, ts, "tustin", prewarp_frequency=w0)``.
``"zoh"``
    Exact zero-order-hold (step-invariant) discretisation ``H(z) = (1 - 1/z) Z{H(s)/s}``,
    computed from the matrix exponential of a state-space realisation.
``"matched"``
    Pole-zero matching: poles and finite zeros map by ``z = exp(s ts)``, zeros at infinity map
    to ``z = 0`` (no added delay) and the gain matches at DC. For the first-order low-pass this
    is ``y[k] = a y[k-1] + (1 - a) x[k]`` with ``a = exp(-ts w0)``, the drive's speed filter of
    :class:`prsa_ctrl.drive.measurement.EncoderDifference`. (python-control's ``"matched"`` puts no
    zero there, i.e. one extra sample of delay per missing zero.)

:meth:`Filter.frequency_response` needs numpy only; :meth:`Filter.continuous_tf` imports
python-control on use.

Examples
--------
>>> f = Notch(centre_hz=500.0, width_hz=200.0, depth_db=-20.0)
>>> bq = f.biquad(2.5e-4)
>>> round(20 * math.log10(abs(complex(bq.frequency_response([2 * math.pi * 500.0])[0]))), 9)
-20.0
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, fields
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._lazy import module
from ..options import check_number
from .sampled import zoh

control = module("control")  # only Filter.continuous_tf needs python-control

__all__ = ["Filter", "DiscreteBiquad", "FirstOrderLowPass", "SecondOrderLowPass", "Notch", "GeneralBiquad",
           "METHODS", "filter_from_dict", "PLACES", "LoopFilter", "loop_filters", "NYQUIST_MARGIN"]

#: Discretisation methods of :meth:`Filter.biquad`.
METHODS = ("tustin", "zoh", "matched")


#: Lowest filter frequency (Hz) a constructor accepts (below it ``1/w0^2`` leaves the float range).
MIN_HZ = 1e-6
#: Lowest ``w0 ts`` (rad per sample, ``w0 = 2 pi f`` at the filter's lowest frequency) that
#: :meth:`Filter.biquad` discretises: below it the biquad's coefficients cancel to round-off
#: (its DC gain is off by ~1e-16/(w0 ts)^2, 1e-6 at this limit) or leave the float range.
MIN_W_TS = 1e-5
#: Fraction of the Nyquist frequency ``1/(2 ts)`` a filter frequency must stay below it in a
#: prewarped Tustin biquad (the loop filters' and the scene's): :meth:`Filter.biquad` refuses
#: frequencies above ``(1 - NYQUIST_MARGIN)/(2 ts)`` there (1980 Hz at 4 kHz). Closer, the
#: prewarping constant ``K = w0 / tan(w0 ts/2)`` goes to 0 and the poles go to ``z = -1`` (a
#: first-order low-pass at ``f``: ``z = -(1 - c)/(1 + c)``, ``c = tan(pi (1/2 - f ts))``; -0.969
#: at the margin, -0.999998 at 1999.999 Hz of 4 kHz; a notch a double pole): the filter does
#: almost nothing at the drive's rate, and the tuner's error sums to infinity need millions of
#: samples (issue 31: prsa-tune ran for minutes on a notch at 1999.99 Hz). Matched, ZOH and
#: unwarped Tustin biquads keep their poles away from -1 and only need ``f < 1/(2 ts)``.
NYQUIST_MARGIN = 0.01


def _shown(v: float) -> str:
    """A frequency as given: every digit (``repr``), ``2500`` for ``2500.0``."""
    s = repr(float(v))
    return s[:-2] if s.endswith(".0") else s


def _hz(name: str, v: object) -> float:
    """A filter frequency (Hz) in ``[MIN_HZ, 1e9]``, or a one-line ValueError naming ``name``."""
    check_number(name, v, 0.0, 1e9, unit="Hz", lo_open=True)
    return check_number(name, v, MIN_HZ, 1e9, unit="Hz")


@dataclass(frozen=True)
class DiscreteBiquad:
    """Normalised discrete biquad ``(b0 + b1/z + b2/z^2) / (1 + a1/z + a2/z^2)`` at sample time
    ``ts`` (s). A first-order section has ``b2 = a2 = 0``.

    Parameters
    ----------
    b0, b1, b2, a1, a2 : float
        Coefficients (dimensionless; ``a0 = 1``).
    ts : float, s
        Sample time.
    """

    b0: float
    b1: float
    b2: float
    a1: float
    a2: float
    ts: float

    def __post_init__(self) -> None:
        for name in ("b0", "b1", "b2", "a1", "a2"):
            object.__setattr__(self, name, check_number(name, getattr(self, name), -1e300, 1e300, lo_open=True))
        object.__setattr__(self, "ts", check_number("ts", self.ts, 0.0, 1e3, unit="s", lo_open=True))

    @property
    def num(self) -> NDArray[np.float64]:
        """``[b0, b1, b2]`` (coefficients of ``z^2, z, 1``)."""
        return np.array([self.b0, self.b1, self.b2])

    @property
    def den(self) -> NDArray[np.float64]:
        """``[1, a1, a2]``."""
        return np.array([1.0, self.a1, self.a2])

    def as_dict(self) -> dict[str, float]:
        """Coefficients as plain floats (``b0 .. a2``, ``a0 = 1`` implied)."""
        return {k: float(getattr(self, k)) for k in ("b0", "b1", "b2", "a1", "a2")}

    @property
    def dc_gain(self) -> float:
        """Gain at ``z = 1``."""
        return float(self.num.sum() / self.den.sum())

    def frequency_response(self, omega: ArrayLike) -> NDArray[np.complex128]:
        """``H(exp(j omega ts))`` at the angular frequencies ``omega`` (rad/s)."""
        zi = np.exp(-1j * np.asarray(omega, float) * self.ts)
        return (self.b0 + zi * (self.b1 + zi * self.b2)) / (1.0 + zi * (self.a1 + zi * self.a2))

    def step(self, x: ArrayLike, initial: str = "rest") -> NDArray[np.float64]:
        """Run the difference equation over the samples ``x``.

        ``y[k] = b0 x[k] + b1 x[k-1] + b2 x[k-2] - a1 y[k-1] - a2 y[k-2]``.

        Parameters
        ----------
        x : array
            Input samples (any unit; the output has the same unit).
        initial : {"rest", "steady"}
            Past samples zero (``"rest"``) or the steady state of a constant input ``x[0]``
            (``"steady"``: past inputs ``x[0]``, past outputs ``dc_gain * x[0]``).

        Returns
        -------
        ndarray
            Output samples, same length as ``x``.
        """
        x = np.asarray(x, float).ravel()
        if initial not in ("rest", "steady"):
            raise ValueError(f"initial = {initial!r}; expected 'rest' or 'steady'")
        x0 = float(x[0]) if (initial == "steady" and x.size) else 0.0
        y0 = self.dc_gain * x0
        x1 = x2 = x0
        y1 = y2 = y0
        y = np.empty_like(x)
        for k, xk in enumerate(x):  # bounded by len(x)
            yk = self.b0 * xk + self.b1 * x1 + self.b2 * x2 - self.a1 * y1 - self.a2 * y2
            x2, x1, y2, y1 = x1, xk, y1, yk
            y[k] = yk
        return y

    def poles(self) -> NDArray[np.complex128]:
        """Roots of ``z^2 + a1 z + a2`` (one for a first-order section)."""
        return np.roots(self.den if self.a2 != 0.0 else self.den[:2]).astype(complex)


class Filter:
    """Common interface of the continuous filters (see the module docstring)."""

    #: Short kind name used in exported files.
    kind: ClassVar[str] = ""

    def coefficients(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """``((n2, n1, n0), (d2, d1, d0))`` of ``H(s)``, ``s`` in rad/s."""
        raise NotImplementedError

    @property
    def characteristic_hz(self) -> float:
        """Frequency (Hz) used for prewarping and the Nyquist check."""
        raise NotImplementedError

    def _highest_hz(self) -> float:
        return self.characteristic_hz

    def _lowest_hz(self) -> float:
        return self.characteristic_hz

    @property
    def order(self) -> int:
        return 2 if self.coefficients()[1][0] != 0.0 else 1

    def parameters(self) -> dict[str, float]:
        """The physical parameters (for export)."""
        raise NotImplementedError

    def continuous_tf(self) -> "control.TransferFunction":
        """``H(s)`` as a python-control transfer function (input and output in the same unit).

        Returns
        -------
        control.TransferFunction
        """
        n, d = self.coefficients()
        if self.order == 1:  # drop the zero s^2 terms so the system stays first order
            n, d = n[1:], d[1:]
        return control.tf(list(n), list(d), name=self.kind)

    def frequency_response(self, omega: ArrayLike, ts: float | None = None, method: str = "tustin",
                           prewarp: bool = True) -> NDArray[np.complex128]:
        """Complex gain at angular frequencies ``omega`` (rad/s), continuous (``ts=None``) or
        of the biquad discretised at ``ts`` (s) with ``method`` (numpy only).

        Parameters
        ----------
        omega : array, rad/s
        ts : float or None, s
        method : {"tustin", "zoh", "matched"}
        prewarp : bool

        Returns
        -------
        ndarray of complex
        """
        if ts is not None:
            return self.biquad(ts, method, prewarp).frequency_response(omega)
        (n2, n1, n0), (d2, d1, d0) = self.coefficients()
        s = 1j * np.asarray(omega, float)
        return (n0 + s * (n1 + s * n2)) / (d0 + s * (d1 + s * d2))

    def _check_nyquist(self, ts: float, margin: bool = True) -> None:
        """Refuse a frequency at or above Nyquist, or (``margin``: a prewarped Tustin biquad)
        within :data:`NYQUIST_MARGIN` of it; and a sample time too short to discretise."""
        hi = self._highest_hz()
        nyq = 0.5 / ts
        if not hi < nyq:
            raise ValueError(f"{self.kind} frequency {_shown(hi)} Hz at ts = {ts:g} s; expected below the Nyquist "
                             f"frequency {nyq:g} Hz")
        if margin and not hi <= nyq * (1.0 - NYQUIST_MARGIN):
            raise ValueError(f"{self.kind} frequency {_shown(hi)} Hz at ts = {ts:g} s; expected below the Nyquist "
                             f"frequency {nyq:g} Hz by at least {NYQUIST_MARGIN:.0%} of it (at most "
                             f"{nyq * (1.0 - NYQUIST_MARGIN):g} Hz) for a prewarped Tustin biquad (closer, its "
                             "poles sit next to z = -1)")
        lo = self._lowest_hz()
        if 2.0 * math.pi * lo * ts < MIN_W_TS:
            raise ValueError(f"ts = {ts!r} s for a {self.kind} at {lo:g} Hz; expected ts >= "
                             f"{MIN_W_TS / (2.0 * math.pi * lo):.3g} s (2 pi f ts >= {MIN_W_TS:g}: shorter sample "
                             "times leave the biquad's coefficients to round-off)")

    def biquad(self, ts: float, method: str = "tustin", prewarp: bool = True) -> DiscreteBiquad:
        """The filter discretised at the sample time ``ts`` (s) as normalised biquad
        coefficients (``a0 = 1``).

        Tustin: ``s = K (z - 1)/(z + 1)``, ``K = w0/tan(w0 ts/2)`` (``prewarp``, ``w0 = 2 pi
        characteristic_hz``) or ``2/ts``; for a second-order ``H`` this gives
        ``b = [n2 K^2 + n1 K + n0, 2 (n0 - n2 K^2), n2 K^2 - n1 K + n0] / A0`` and the same
        for ``a`` with ``d``, ``A0 = d2 K^2 + d1 K + d0``; first order:
        ``b = [n1 K + n0, n0 - n1 K, 0] / A0``, ``A0 = d1 K + d0``. ZOH: exact
        step-invariant discretisation. Matched: ``z = exp(s ts)`` for poles and finite zeros,
        zeros at infinity at ``z = 0``, DC gain matched (``prewarp`` is ignored by both).

        Parameters
        ----------
        ts : float, s
            Sample time; the filter's frequencies must lie below ``1/(2 ts)`` (prewarped
            Tustin: by at least :data:`NYQUIST_MARGIN` of it, see there).
        method : {"tustin", "zoh", "matched"}
        prewarp : bool
            Tustin only.

        Returns
        -------
        DiscreteBiquad
        """
        ts = check_number("ts", ts, 0.0, 1e3, unit="s", lo_open=True)
        if method not in METHODS:
            raise ValueError(f"method = {method!r}; expected one of {', '.join(METHODS)}")
        if not isinstance(prewarp, bool):
            raise ValueError(f"prewarp = {prewarp!r}; expected True or False")
        self._check_nyquist(ts, margin=method == "tustin" and prewarp)
        (n2, n1, n0), (d2, d1, d0) = self.coefficients()
        if method == "tustin":
            w0 = 2.0 * math.pi * self.characteristic_hz
            k = w0 / math.tan(w0 * ts / 2.0) if prewarp else 2.0 / ts
            if self.order == 2:
                kk = k * k
                b = [n2 * kk + n1 * k + n0, 2.0 * (n0 - n2 * kk), n2 * kk - n1 * k + n0]
                a = [d2 * kk + d1 * k + d0, 2.0 * (d0 - d2 * kk), d2 * kk - d1 * k + d0]
            else:
                b = [n1 * k + n0, n0 - n1 * k, 0.0]
                a = [d1 * k + d0, d0 - d1 * k, 0.0]
        elif method == "zoh":
            b, a = self._zoh(ts)
        else:
            b, a = self._matched(ts)
        a0 = a[0]
        c = [b[0] / a0, b[1] / a0, b[2] / a0, a[1] / a0, a[2] / a0]
        if not all(math.isfinite(x) for x in c):  # guarded above; never a "b0 = nan" from here
            raise ValueError(f"ts = {ts!r} s with {self!r} ({method}): non-finite biquad coefficients; expected a "
                             "sample time within the filter's range")
        return DiscreteBiquad(*c, ts)

    def _zoh(self, ts: float) -> tuple[list[float], list[float]]:
        (n2, n1, n0), (d2, d1, d0) = self.coefficients()
        if self.order == 2:  # controllable canonical form of (n2 s^2 + n1 s + n0)/(s^2 + ...)
            n2, n1, n0, d1, d0 = n2 / d2, n1 / d2, n0 / d2, d1 / d2, d0 / d2
            a = np.array([[-d1, -d0], [1.0, 0.0]])
            bvec = np.array([[1.0], [0.0]])
            c = np.array([[n1 - n2 * d1, n0 - n2 * d0]])
            dd = n2
        else:
            a = np.array([[-d0 / d1]])
            bvec = np.array([[1.0]])
            c = np.array([[n0 / d1 - n1 * d0 / d1 / d1]])
            dd = n1 / d1
        ad, bd = zoh(a, bvec, ts)
        den = np.poly(ad)
        num = np.poly(ad - bd @ c) - den + dd * den  # C (zI - A)^-1 B + D over det(zI - A)
        pad = [0.0] * (3 - len(den))
        return list(num) + pad, list(den) + pad

    def _matched(self, ts: float) -> tuple[list[float], list[float]]:
        (n2, n1, n0), (d2, d1, d0) = self.coefficients()
        poles = np.roots([d2, d1, d0] if self.order == 2 else [d1, d0])
        zeros = np.roots(np.trim_zeros([n2, n1, n0], "f"))
        zp = np.exp(poles * ts)
        zz = np.concatenate([np.exp(zeros * ts), np.zeros(len(poles) - len(zeros))])
        den = np.real(np.poly(zp))
        num = np.real(np.poly(zz))
        num = num * (den.sum() / num.sum()) * (n0 / d0)  # DC gain matched
        pad = [0.0] * (3 - len(den))
        return list(num) + pad, list(den) + pad

    def step(self, x: ArrayLike, ts: float, method: str = "tustin", prewarp: bool = True,
             initial: str = "rest") -> NDArray[np.float64]:
        """Filter the samples ``x`` (taken every ``ts`` s) with the discretised biquad; see
        :meth:`DiscreteBiquad.step`."""
        return self.biquad(ts, method, prewarp).step(x, initial)

    def as_dict(self, ts: float | None = None, method: str = "tustin", prewarp: bool = True) -> dict:
        """Kind, parameters, continuous coefficients and (with ``ts``) the biquad."""
        (n2, n1, n0), (d2, d1, d0) = self.coefficients()
        out: dict = {"kind": self.kind, **self.parameters(),
                     "continuous_num_s": [n2, n1, n0], "continuous_den_s": [d2, d1, d0]}
        if ts is not None:
            bq = self.biquad(ts, method, prewarp)
            out["discretisation"] = method + (" (prewarped at the characteristic frequency)"
                                              if method == "tustin" and prewarp else "")
            out["biquad"] = bq.as_dict()
        return out

    def to_dict(self, ts: float | None = None, method: str = "tustin", prewarp: bool = True) -> dict:
        """Deprecated alias of :meth:`as_dict` (kept for existing callers and notebooks)."""
        return self.as_dict(ts, method, prewarp)


@dataclass(frozen=True)
class FirstOrderLowPass(Filter):
    """``H(s) = 1 / (1 + s/w0)``, ``w0 = 2 pi corner_hz``.

    Parameters
    ----------
    corner_hz : float, Hz
        -3 dB corner frequency.

    Examples
    --------
    >>> bq = FirstOrderLowPass(1 / (2 * math.pi * 2e-4)).biquad(2.5e-4, "matched")
    >>> a = math.exp(-2.5e-4 / 2e-4)  # the drive's speed filter y = a y + (1 - a) x
    >>> abs(bq.a1 + a) < 1e-15, abs(bq.b0 - (1 - a)) < 1e-15, bq.b1, bq.b2
    (True, True, 0.0, 0.0)
    """

    corner_hz: float
    kind: ClassVar[str] = "lowpass1"

    def __post_init__(self) -> None:
        _hz("corner_hz", self.corner_hz)

    @classmethod
    def from_time_constant(cls, tau_s: float) -> "FirstOrderLowPass":
        """Low-pass with time constant ``tau_s`` (s): ``corner_hz = 1/(2 pi tau_s)``."""
        return cls(1.0 / (2.0 * math.pi * check_number("tau_s", tau_s, 0.0, 1e5, unit="s", lo_open=True)))

    @property
    def characteristic_hz(self) -> float:
        return float(self.corner_hz)

    def coefficients(self):
        w0 = 2.0 * math.pi * self.corner_hz
        return (0.0, 0.0, 1.0), (0.0, 1.0 / w0, 1.0)

    def parameters(self) -> dict[str, float]:
        return {"corner_hz": float(self.corner_hz), "time_constant_s": 1.0 / (2.0 * math.pi * self.corner_hz)}


@dataclass(frozen=True)
class SecondOrderLowPass(Filter):
    """``H(s) = w0^2 / (s^2 + 2 damping w0 s + w0^2)``, ``w0 = 2 pi corner_hz``.

    Parameters
    ----------
    corner_hz : float, Hz
        Natural frequency.
    damping : float
        Damping ratio (0.7071 gives a Butterworth response, -3 dB at ``corner_hz``).
    """

    corner_hz: float
    damping: float = 1.0 / math.sqrt(2.0)
    kind: ClassVar[str] = "lowpass2"

    def __post_init__(self) -> None:
        _hz("corner_hz", self.corner_hz)
        check_number("damping", self.damping, 0.0, 100.0, lo_open=True)

    @property
    def characteristic_hz(self) -> float:
        return float(self.corner_hz)

    def coefficients(self):
        w0 = 2.0 * math.pi * self.corner_hz
        return (0.0, 0.0, 1.0), (1.0 / w0**2, 2.0 * self.damping / w0, 1.0)

    def parameters(self) -> dict[str, float]:
        return {"corner_hz": float(self.corner_hz), "damping": float(self.damping)}


@dataclass(frozen=True)
class Notch(Filter):
    """``H(s) = (s^2 + 2 g zeta w0 s + w0^2) / (s^2 + 2 zeta w0 s + w0^2)``, ``w0 = 2 pi
    centre_hz``, ``zeta = width_hz / (2 centre_hz)`` (the -3 dB width of the full notch),
    ``g = 10^(depth_db/20)`` the gain at the centre.

    Parameters
    ----------
    centre_hz : float, Hz
        Centre frequency.
    width_hz : float, Hz
        Width ``2 zeta centre_hz`` (quality ``centre_hz/width_hz``).
    depth_db : float, dB
        Gain at the centre, ``<= 0`` (``-inf`` is not allowed: use e.g. -60 dB).
    """

    centre_hz: float
    width_hz: float
    depth_db: float = -20.0
    kind: ClassVar[str] = "notch"

    def __post_init__(self) -> None:
        _hz("centre_hz", self.centre_hz)
        check_number("width_hz", self.width_hz, 0.0, 4.0 * self.centre_hz, unit="Hz (up to 4 x centre_hz)", lo_open=True)
        check_number("depth_db", self.depth_db, -120.0, 0.0, unit="dB", lo_open=False)

    @classmethod
    def from_quality(cls, centre_hz: float, quality: float, depth_db: float = -20.0) -> "Notch":
        """Notch with quality ``Q = centre_hz / width_hz``."""
        q = check_number("quality", quality, 0.25, 1e6, lo_open=True)
        return cls(centre_hz, check_number("centre_hz", centre_hz, 0.0, 1e9, unit="Hz", lo_open=True) / q, depth_db)

    @property
    def quality(self) -> float:
        return float(self.centre_hz / self.width_hz)

    @property
    def characteristic_hz(self) -> float:
        return float(self.centre_hz)

    def coefficients(self):
        w0 = 2.0 * math.pi * self.centre_hz
        zeta = self.width_hz / (2.0 * self.centre_hz)
        g = 10.0 ** (self.depth_db / 20.0)
        return (1.0 / w0**2, 2.0 * g * zeta / w0, 1.0), (1.0 / w0**2, 2.0 * zeta / w0, 1.0)

    def parameters(self) -> dict[str, float]:
        return {"centre_hz": float(self.centre_hz), "width_hz": float(self.width_hz),
                "depth_db": float(self.depth_db), "quality": self.quality}


@dataclass(frozen=True)
class GeneralBiquad(Filter):
    """The drives' general second-order filter with unit DC gain,
    ``H(s) = (s^2/wz^2 + 2 zeta_z s/wz + 1) / (s^2/wp^2 + 2 zeta_p s/wp + 1)``,
    ``wz = 2 pi zero_hz``, ``wp = 2 pi pole_hz`` (a notch is ``zero_hz = pole_hz``).

    Parameters
    ----------
    zero_hz, pole_hz : float, Hz
        Numerator and denominator natural frequencies.
    zero_damping, pole_damping : float
        Numerator (``>= 0``) and denominator (``> 0``) damping ratios.
    """

    zero_hz: float
    zero_damping: float
    pole_hz: float
    pole_damping: float
    kind: ClassVar[str] = "biquad"

    def __post_init__(self) -> None:
        _hz("zero_hz", self.zero_hz)
        check_number("zero_damping", self.zero_damping, 0.0, 100.0, lo_open=False)
        _hz("pole_hz", self.pole_hz)
        check_number("pole_damping", self.pole_damping, 0.0, 100.0, lo_open=True)

    @property
    def characteristic_hz(self) -> float:
        return float(self.pole_hz)

    def _highest_hz(self) -> float:
        return float(max(self.zero_hz, self.pole_hz))

    def _lowest_hz(self) -> float:
        return float(min(self.zero_hz, self.pole_hz))

    def coefficients(self):
        wz, wp = 2.0 * math.pi * self.zero_hz, 2.0 * math.pi * self.pole_hz
        return (1.0 / wz**2, 2.0 * self.zero_damping / wz, 1.0), (1.0 / wp**2, 2.0 * self.pole_damping / wp, 1.0)

    def parameters(self) -> dict[str, float]:
        return {"zero_hz": float(self.zero_hz), "zero_damping": float(self.zero_damping),
                "pole_hz": float(self.pole_hz), "pole_damping": float(self.pole_damping)}


_KINDS = {c.kind: c for c in (FirstOrderLowPass, SecondOrderLowPass, Notch, GeneralBiquad)}


def filter_from_dict(d: dict) -> Filter:
    """A filter from ``{"kind": ..., parameters...}`` (the inverse of :meth:`Filter.as_dict`,
    derived entries ignored).

    Parameters
    ----------
    d : dict
        ``kind`` one of ``lowpass1, lowpass2, notch, biquad`` and that filter's parameters.

    Returns
    -------
    Filter
    """
    if not isinstance(d, dict) or d.get("kind") not in _KINDS:
        got = d.get("kind") if isinstance(d, dict) else d
        raise ValueError(f"filter kind = {got!r}; expected one of {', '.join(_KINDS)}")
    cls = _KINDS[d["kind"]]
    names = [f.name for f in fields(cls)]
    missing = [f.name for f in fields(cls) if f.name not in d and f.default is MISSING]
    if missing:
        raise ValueError(f"filter {d['kind']!r} lacks {', '.join(missing)}; expected {', '.join(names)}")
    return cls(**{n: d[n] for n in names if n in d})


#: Where a filter sits in the drive's sampled loop (:func:`prsa_ctrl.sim.engine.run`): on the
#: measured speed the PID acts on, or on the PID's torque command before the one-sample
#: computation delay and zero-order hold.
PLACES = ("speed_measurement", "torque_command")


@dataclass(frozen=True)
class LoopFilter:
    """A filter placed in the drive's sampled speed loop, run as the discrete biquad
    :meth:`Filter.biquad` gives at the plant's sample time (what the drive export writes).

    ``place = "speed_measurement"``: the speed the PID acts on (proportional, integral and
    derivative paths) is the measurement block's speed through this biquad.
    ``place = "torque_command"``: the PID's (limited) command goes through this biquad and is
    limited again to the torque limit before the one-sample delay and zero-order hold; the
    biquad's own recursion runs on its unlimited output. Several filters at one place run in
    series in the order given.

    Parameters
    ----------
    filter : Filter
        The continuous filter (unit DC gain).
    place : {"speed_measurement", "torque_command"}
    method : {"tustin", "zoh", "matched"}
        Discretisation (:meth:`Filter.biquad`).
    prewarp : bool
        Tustin prewarped at the filter's characteristic frequency.

    Examples
    --------
    >>> lf = LoopFilter(Notch(300.0, 120.0, -20.0), "torque_command")
    >>> round(abs(complex(lf.biquad(2.5e-4).frequency_response([2 * math.pi * 300.0])[0])), 9)
    0.1
    """

    filter: Filter
    place: str = "torque_command"
    method: str = "tustin"
    prewarp: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.filter, Filter):
            raise ValueError(f"filter = {self.filter!r}; expected a Filter (FirstOrderLowPass, SecondOrderLowPass, "
                             "Notch or GeneralBiquad)")
        if self.place not in PLACES:
            raise ValueError(f"filter place = {self.place!r}; expected one of {', '.join(PLACES)}")
        if self.method not in METHODS:
            raise ValueError(f"filter method = {self.method!r}; expected one of {', '.join(METHODS)}")
        if not isinstance(self.prewarp, bool):
            raise ValueError(f"filter prewarp = {self.prewarp!r}; expected True or False")

    def biquad(self, ts: float) -> DiscreteBiquad:
        """The biquad the drive runs at the sample time ``ts`` (s)."""
        return self.filter.biquad(ts, self.method, self.prewarp)

    def as_dict(self, ts: float | None = None) -> dict:
        """:meth:`Filter.as_dict` with the place (and the discretisation used in the loop)."""
        return {"place": self.place, **self.filter.as_dict(ts, self.method, self.prewarp)}

    def to_dict(self, ts: float | None = None) -> dict:
        """Deprecated alias of :meth:`as_dict` (kept for existing callers and notebooks)."""
        return self.as_dict(ts)


def loop_filters(filters: object, ts: float | None = None) -> tuple[LoopFilter, ...]:
    """Normalise a user's filter list: ``LoopFilter`` items, ``(place, Filter)`` pairs or a bare
    ``Filter`` (placed on the torque command, as the drive export places it); with ``ts`` (s) each biquad is formed once so
    that a frequency at or above Nyquist is refused here, with one line.

    Parameters
    ----------
    filters : sequence or None
    ts : float, optional, s

    Returns
    -------
    tuple of LoopFilter
    """
    if filters is None:
        return ()
    if isinstance(filters, (Filter, LoopFilter)):
        filters = [filters]
    if isinstance(filters, (str, bytes, dict)) or not hasattr(filters, "__iter__"):
        raise ValueError(f"filters = {filters!r}; expected a list of LoopFilter or (place, Filter) pairs")
    out = []
    for item in filters:
        if isinstance(item, LoopFilter):
            lf = item
        elif isinstance(item, Filter):
            lf = LoopFilter(item)
        elif isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], str):
            lf = LoopFilter(item[1], item[0])
        else:
            raise ValueError(f"filter entry = {item!r}; expected a LoopFilter, a Filter or a (place, Filter) pair")
        if ts is not None:
            lf.biquad(ts)
        out.append(lf)
    if len(out) > 8:
        raise ValueError(f"{len(out)} filters; expected at most 8 in one loop")
    return tuple(out)
