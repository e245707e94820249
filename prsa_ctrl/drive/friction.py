"""Friction feed-forward: the calibrated plant's sliding-friction curve as a torque the drive adds.

The drive knows the motion profile's speed ``v_ref`` (m/s of screw travel; nut speed
``w = v_ref / a`` rad/s with ``a`` the lead per radian) before the axis moves; the friction
the axis will meet at that speed is the plant file's friction model evaluated there. Adding it
to the torque command (as the acceleration feed-forward adds ``J a_ref``) leaves the speed PI
only the unmodelled part, which shrinks the following error where friction dominates (slow
moves, starts from rest, low inertia torque). Per direction (``+`` for ``w > 0``, ``-`` for
``w < 0``), in N m on the nut/motor shaft::

    tau_f(w) = +g (C+ + S+ exp(-(w/w_s)^2) + V+ w)      w > 0
             = -g (C- + S- exp(-(w/w_s)^2) - V- w)      w < 0
             = 0                                         w = 0 (at rest the integral holds)

``C`` Coulomb (sliding) level, ``S`` Stribeck excess at zero speed, ``w_s`` Stribeck speed,
``V`` viscous coefficient, ``g`` a gain (1 = the full model). :meth:`FrictionFeedforward.from_plant`
fills them from the plant's friction keys at a given axial load (the thread friction of a
screw grows with the load: ``C = k mu_d |F| (f_N + f_S) + T0``, ``S = k (mu_s - mu_d) |F| (f_N + f_S)
+ (T_s0 - T0)`` with the drag's breakaway level ``T_s0`` (``friction.no_load_breakaway_torque_n_m``),
``w_s = v_s / a``, ``V = c_v``, plus and minus a drag offset ``friction.torque_offset_n_m``
where the plant has one; a ``linear-axis`` plant has the fitted Coulomb and viscous
coefficients per direction). It equals the plant's sliding friction (prsa_ctrl.plant.model,
Stribeck curve beyond Karnopp's stick band) at the reference speed; inside the stick band the
plant sticks and no feed-forward can act on the error anyway.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from ..options import check_number

if TYPE_CHECKING:
    from ..plant.plantfile import Plant

__all__ = ["FrictionFeedforward"]


@dataclass(frozen=True)
class FrictionFeedforward:
    """The friction curve the drive feeds forward (N m on the nut/motor shaft, rad/s).

    Parameters
    ----------
    coulomb_positive_n_m, coulomb_negative_n_m : float, N m
        Sliding (Coulomb) friction level in the positive / negative direction (magnitudes).
    stribeck_positive_n_m, stribeck_negative_n_m : float, N m
        Stribeck excess at zero speed (breakaway minus sliding level; magnitudes).
    stribeck_speed_rad_s : float, rad/s
        Speed over which the Stribeck excess decays (``exp(-(w/w_s)^2)``).
    viscous_positive_n_m_s_per_rad, viscous_negative_n_m_s_per_rad : float, N m s/rad
        Viscous coefficient per direction.
    gain : float
        Fraction of the model fed forward (0 to 2; 1 = the full model).
    source : str
        Where the numbers come from (plant file, load).

    Examples
    --------
    >>> ff = FrictionFeedforward(0.1, 0.12, 0.02, 0.02, 0.5, 1e-4, 1e-4)
    >>> round(float(ff.torque(10.0)), 6), round(float(ff.torque(-10.0)), 6), float(ff.torque(0.0))
    (0.101, -0.121, 0.0)
    """

    coulomb_positive_n_m: float
    coulomb_negative_n_m: float
    stribeck_positive_n_m: float = 0.0
    stribeck_negative_n_m: float = 0.0
    stribeck_speed_rad_s: float = 1.0
    viscous_positive_n_m_s_per_rad: float = 0.0
    viscous_negative_n_m_s_per_rad: float = 0.0
    gain: float = 1.0
    source: str = ""

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name == "source":
                continue
            check_number(f"FrictionFeedforward {f.name}", getattr(self, f.name), 0.0,
                         lo_open=f.name == "stribeck_speed_rad_s")
        if self.gain > 2.0:
            raise ValueError(f"FrictionFeedforward gain = {self.gain!r}; expected a finite number in [0, 2]")

    @classmethod
    def from_plant(cls, plant: "Plant", load_n: float = 0.0, gain: float = 1.0) -> "FrictionFeedforward":
        """The plant file's sliding friction at axial load ``load_n`` (N) as a feed-forward.

        Parameters
        ----------
        plant : Plant
        load_n : float, N
            Axial load the friction is computed at (a screw's thread friction grows with ``|F|``;
            the load the axis carries while it moves, e.g. a constant process force).
        gain : float
            Fraction fed forward (1 = the full model).

        Returns
        -------
        FrictionFeedforward
        """
        if isinstance(load_n, bool) or not isinstance(load_n, (int, float)) or not math.isfinite(load_n):
            raise ValueError(f"load_n = {load_n!r}; expected a finite axial load in N")
        v = plant.values
        a = plant.lead_per_rad
        f_n, f_s = plant.normal_force_factor()
        k = plant.slip_arm_m
        t0 = v["friction.no_load_torque_n_m"]
        mu_s, mu_d = v["friction.static"], v["friction.dynamic"]
        if plant.mechanism == "linear-axis":
            # load coordinates (a = 1 m/rad): the constant offset (Fc+ - Fc-)/2 acts like a load
            offset = 0.5 * (v["friction.coulomb_positive_n"] - v["friction.coulomb_negative_n"])
            normal = abs(load_n + offset) * (f_n + f_s)
            vp, vn = v["friction.viscous_positive_n_s_per_m"], v["friction.viscous_negative_n_s_per_m"]
        else:
            # a drag offset T_o (friction.torque_offset_n_m, where the plant has the key) makes the
            # Coulomb levels T_0 + T_o forward and T_0 - T_o backward (in N m: a = 1 below)
            offset, normal = v.get("friction.torque_offset_n_m", 0.0) / a, abs(load_n) * (f_n + f_s)
            b_o = v.get("friction.viscous_offset_n_m_s_per_rad", 0.0)  # direction-dependent viscous part
            vp, vn = v["friction.viscous_n_m_s_per_rad"] + b_o, v["friction.viscous_n_m_s_per_rad"] - b_o
        slide = k * mu_d * normal + t0
        excess = k * (mu_s - mu_d) * normal
        from ..plant.model import drag_breakaway_excess  # CasADi: only on this path

        drag_excess = drag_breakaway_excess(plant)  # the no-load drag's breakaway excess T_s0 - T_0
        if drag_excess is not None:
            excess = excess + drag_excess
        return cls(coulomb_positive_n_m=slide + offset * a, coulomb_negative_n_m=slide - offset * a,
                   stribeck_positive_n_m=max(excess, 0.0), stribeck_negative_n_m=max(excess, 0.0),
                   stribeck_speed_rad_s=v["friction.stribeck_velocity_m_s"] / a,
                   viscous_positive_n_m_s_per_rad=vp, viscous_negative_n_m_s_per_rad=vn, gain=gain,
                   source=f"plant {plant.name} friction keys at an axial load of {load_n:g} N")

    def key(self) -> tuple:
        """The numbers that define the compiled law (the curve is built into it)."""
        return tuple(float(getattr(self, f.name)) for f in fields(self) if f.name != "source")

    def torque(self, w: Any) -> Any:
        """Feed-forward torque (N m) at nut speed ``w`` (rad/s; number or array), numpy."""
        return self._law(np.asarray(w, dtype=float), np.exp, np.where)

    def symbolic(self, w: Any) -> Any:
        """The same as :meth:`torque` on a CasADi expression (the sampled drive law)."""
        import casadi as ca

        return self._law(w, ca.exp, ca.if_else)

    def _law(self, w: Any, exp: Any, select: Any) -> Any:
        """The curve with the array library's ``exp`` and ``select(condition, a, b)``."""
        shape = exp(-((w / self.stribeck_speed_rad_s) ** 2))
        pos = self.coulomb_positive_n_m + self.stribeck_positive_n_m * shape + self.viscous_positive_n_m_s_per_rad * w
        neg = self.coulomb_negative_n_m + self.stribeck_negative_n_m * shape - self.viscous_negative_n_m_s_per_rad * w
        return self.gain * select(w > 0, pos, select(w < 0, -neg, 0.0))

    def table(self, speeds_rad_s: Any) -> list[list[float]]:
        """``[[speed rad/s, torque N m], ...]`` for a drive that interpolates a table."""
        w = np.asarray(speeds_rad_s, dtype=float)
        return [[float(a), float(b)] for a, b in zip(w, self.torque(w))]

    def as_dict(self, max_speed_rad_s: float | None = None, points: int = 21) -> dict:
        """Plain data for an export: the formula, its coefficients and (with ``max_speed_rad_s``)
        a table from ``-max`` to ``+max``."""
        out: dict[str, Any] = {
            "formula": "w > 0: g (C+ + S+ exp(-(w/w_s)^2) + V+ w); w < 0: -g (C- + S- exp(-(w/w_s)^2) - V- w); "
                       "w = 0: 0 (w: the reference speed of the nut/motor, rad/s; torque N m added to the command)",
            **{k: v for k, v in asdict(self).items()}}
        if max_speed_rad_s is not None:
            out["table_speed_rad_s_torque_n_m"] = self.table(np.linspace(-max_speed_rad_s, max_speed_rad_s, points))
            out["table_note"] = ("the curve jumps at w = 0 (Coulomb friction changes sign): interpolate within each "
                                 "sign's half only and apply 0 at w = 0; between the table's first non-zero speed and "
                                 "0 use the formula (Stribeck part)")
        return out
