"""Text writers of the drive law (:class:`prsa_ctrl.io.codegen.DriveLaw`): C99 for firmware,
IEC 61131-3 Structured Text, and the helpers that keep user text inert and real literals IEC.

See :mod:`prsa_ctrl.io.codegen` for the law itself and :func:`prsa_ctrl.io.codegen.export_code`
for the files. Everything here is pure text generation (no compiler, no I/O).
"""

from __future__ import annotations

import math
import re
from typing import Any, Iterable

from .drivelaw import DriveLaw

__all__ = ["inert_text", "iec_real", "is_code_name", "check_header_name", "IEC_RESERVED", "REAL_TYPES", "FLUSH",
           "c_code", "st_code", "st_parts",
           "law_constants", "assumption_lines"]

#: Floating-point types of the generated code: C type -> ST type.
REAL_TYPES = {"double": "LREAL", "float": "REAL"}


# --- inert text ---------------------------------------------------------------------------------

def inert_text(text: Any, limit: int = 200) -> str:
    r"""User text (a plant name, a template field) made inert for any comment or string of the
    generated files: printable ASCII only (every other character -- control characters, line
    breaks, non-ASCII and characters outside the Basic Multilingual Plane alike -- becomes
    ``\u{hex}``), and the characters of the comment and string delimiters of C, C++,
    Structured Text and XML (``*``, ``/``, ``(``, ``)``, quotes, backslash, ``<``, ``>``, ``&``,
    ``$``, ``?`` and the second ``-`` of ``--``) spelled as ``\u{hex}`` too, so the result can
    close nothing and open nothing; cut to ``limit`` characters (``...`` marks a cut).

    >>> print(inert_text('Axis 3 */ __asm__("id"); /* rev B'))
    Axis 3 \u{2a}\u{2f} __asm__\u{28}\u{22}id\u{22}\u{29}; \u{2f}\u{2a} rev B
    """
    s = str(text)
    cut = len(s) > limit
    out = []
    for ch in s[:limit]:
        out.append(ch if " " <= ch <= "~" and ch not in "*/()\\\"'<>&$?" else "\\u{%x}" % ord(ch))
    r = "".join(out)
    while "--" in r:
        r = r.replace("--", "-\\u{2d}")
    return r + ("..." if cut else "")


# --- code writers -------------------------------------------------------------------------------

def _lit(v: float) -> str:
    """A C floating literal that reads back as exactly ``v`` (double)."""
    if not math.isfinite(float(v)):
        raise ValueError(f"constant {v!r}; expected a finite number")
    return iec_real(v)


def iec_real(v: float) -> str:
    """``v`` as an IEC 61131-3 real literal (``digits '.' digits [E exp]``, also valid C) that
    reads back as exactly ``v`` in double: ``1e-07`` -> ``1.0E-7``, ``0.085`` -> ``0.085``.

    >>> iec_real(1e-07), iec_real(2.5e-4), iec_real(3.0), iec_real(-1.5e300)
    ('1.0E-7', '0.00025', '3.0', '-1.5E+300')
    """
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"constant {v!r}; expected a finite number")
    r = repr(f)
    if "e" in r or "E" in r:
        mant, exp = r.lower().split("e")
        if "." not in mant:
            mant += ".0"
        e = int(exp)
        return f"{mant}E{'+' if e >= 0 else '-'}{abs(e)}"
    return r if "." in r else r + ".0"


def is_code_name(name: Any) -> bool:
    """Whether ``name`` can name the generated code: a C and IEC 61131-3 identifier (a letter, then
    letters, digits and single underscores, at most 40 characters) that is no IEC keyword or
    standard function (block) name (:data:`IEC_RESERVED`, compared case-insensitively)."""
    return (isinstance(name, str) and len(name) <= 40 and re.fullmatch(r"[A-Za-z][A-Za-z0-9]*(_[A-Za-z0-9]+)*", name)
            is not None and name.upper() not in IEC_RESERVED)


def check_header_name(header: Any) -> str:
    """The file name ``#include "..."`` takes: no quote, backslash or control character (so it
    cannot end the include), at most 200 characters; ValueError otherwise."""
    if not isinstance(header, str) or not re.fullmatch(r'[^"\\\x00-\x1f\x7f]{1,200}', header):
        raise ValueError(f"header = {header!r}; expected a file name without quotes, backslashes or control "
                         "characters (it goes into #include \"...\")")
    return header


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*(_[A-Za-z0-9]+)*", name) or len(name) > 40:
        raise ValueError(f"name = {name!r}; expected an identifier (a letter, then letters, digits and single "
                         "underscores; at most 40 characters)")
    if name.upper() in IEC_RESERVED:
        raise ValueError(f"name = {name!r}; expected a name that is no IEC 61131-3 keyword or standard function "
                         "(block) name")
    return name


def _check_real(real: str) -> str:
    if real not in REAL_TYPES:
        raise ValueError(f"real = {real!r}; expected one of {', '.join(REAL_TYPES)}")
    return real


def _check_differences(differences: str) -> bool:
    if differences != "counts":
        raise ValueError(f"differences = {differences!r}; expected 'counts' (wrap-safe integer differences; the "
                         "'angle' variant, which needed unwrapped 64-bit counts, was removed)")
    return True


#: Keywords and standard function / function-block names of IEC 61131-3 (and matiec's library)
#: that a generated name must not take (ST is case-insensitive).
IEC_RESERVED = frozenset("""
ACTION END_ACTION ARRAY OF AT CASE END_CASE CONFIGURATION END_CONFIGURATION CONSTANT DO ELSE ELSIF END_FOR END_IF
END_REPEAT END_WHILE EXIT F_EDGE R_EDGE FALSE TRUE FOR TO BY FUNCTION END_FUNCTION FUNCTION_BLOCK END_FUNCTION_BLOCK
IF THEN INITIAL_STEP END_STEP NON_RETAIN PROGRAM END_PROGRAM READ_ONLY READ_WRITE REPEAT UNTIL RESOURCE END_RESOURCE
RETAIN RETURN STEP STRUCT END_STRUCT TASK TRANSITION END_TRANSITION TYPE END_TYPE VAR END_VAR VAR_ACCESS VAR_CONFIG
VAR_EXTERNAL VAR_GLOBAL VAR_INPUT VAR_IN_OUT VAR_OUTPUT VAR_TEMP WHILE WITH PRIORITY SINGLE INTERVAL ON FROM
BOOL SINT INT DINT LINT USINT UINT UDINT ULINT REAL LREAL TIME DATE TIME_OF_DAY TOD DATE_AND_TIME DT STRING WSTRING
BYTE WORD DWORD LWORD ANY ANY_NUM ANY_REAL ANY_INT ANY_BIT ANY_DATE EN ENO AND OR XOR NOT MOD
ABS SQRT LN LOG EXP SIN COS TAN ASIN ACOS ATAN EXPT ADD SUB MUL DIV MOVE SHL SHR ROR ROL SEL MAX MIN LIMIT MUX
GT GE EQ LE LT NE LEN LEFT RIGHT MID CONCAT INSERT DELETE REPLACE FIND TRUNC
SR RS SEMA R_TRIG F_TRIG CTU CTD CTUD TP TON TOF RTC INTEGRAL DERIVATIVE PID RAMP HYSTERESIS
""".split())


def law_constants(law: "DriveLaw") -> list[tuple[str, float, str]]:
    """``(field, value, comment)`` of every run-time parameter (C field names; ST adds ``P_``)."""
    c = [("ts", law.ts, "sample time, s"),
         ("torque_max", law.torque_limit_n_m, "upper torque limit, N m"),
         ("torque_min", -law.torque_limit_n_m, "lower torque limit, N m (<= torque_max)"),
         ("rad_per_count", law.rad_per_count, "encoder: rad per count (2 pi/counts per rev)"),
         ("a_w", law.speed_filter_a, "speed filter a = exp(-Ts/tau_w)"),
         ("one_minus_a_w", 1 - law.speed_filter_a, "1 - a"),
         ("kp", law.kp, "speed PI proportional gain, N m s/rad"),
         ("b_sp", law.setpoint_weight, "2-DOF setpoint weight b (u = kp (b w_ref - w) + I ...)"),
         ("ki", law.ki, "speed PI integral gain, N m/rad"),
         ("kd", law.kd, "derivative gain, N m s^2/rad (on the measured speed; 0: derivative path skipped)"),
         ("beta", law.beta, "derivative filter beta = exp(-Ts/tf)"),
         ("one_minus_beta", 1 - law.beta, "1 - beta"),
         ("k_aw", law.anti_windup_per_s, "anti-windup (back-calculation) gain ki/max(kp, 1e-9), 1/s"),
         ("tau_ff", law.torque_ff_n_m, "constant torque feed-forward, N m")]
    for place, bqs in (("sf", law.speed_biquads), ("tf", law.torque_biquads)):
        for i, b in enumerate(bqs):
            for k, v in zip(("b0", "b1", "b2", "a1", "a2"), b):
                c.append((f"{place}{i}_{k}", v, f"{'speed-measurement' if place == 'sf' else 'torque-command'} "
                                                f"biquad {i + 1}: {k}"))
    p = law.position
    if p is not None:
        c += [("tp_kip", (p.rate * law.ts) * p.ki, "position-loop sample time x position integral gain, 1/s"),
              ("kv", p.kv, "position gain Kv, 1/s"),
              ("kvff", p.kvff, "velocity feed-forward gain"),
              ("kaff_j", p.kaff * p.inertia_kg_m2, "acceleration feed-forward kaff J, kg m^2"),
              ("lead", p.lead_m_per_rad, "screw lead per nut radian, m/rad"),
              ("unit_m", p.unit_m, "m of travel per unit of the measured position"),
              ("err_to_rad", p.err_to_rad, "nut rad per unit of position error"),
              ("pos_per_count", p.per_count, "measured position per count (rad or m)")]
        if p.friction is not None:
            c += [(f"fr_{k}", v, f"friction feed-forward: {what}") for k, v, what in zip(
                ("cp", "cn", "sp", "sn", "ws", "vp", "vn", "g"), p.friction,
                ("Coulomb level, positive direction, N m", "Coulomb level, negative direction, N m",
                 "Stribeck excess, positive direction, N m", "Stribeck excess, negative direction, N m",
                 "Stribeck speed, rad/s", "viscous, positive direction, N m s/rad",
                 "viscous, negative direction, N m s/rad", "gain (1 = the plant's full friction model)"))]
    return c


#: Flush threshold of the recursive states (no subnormal numbers at rest), in the states' units.
FLUSH = 1e-30


def assumption_lines(law: "DriveLaw") -> list[str]:
    """The law's plant assumptions as text lines; the plant file's source texts made inert."""
    return [f"{k}: {v}" + (f" [source: {inert_text(src, 160)}]" if src else "") for k, v, src in law.assumptions]


def _header_comment(law: "DriveLaw", lang: str) -> list[str]:
    from .. import __version__

    p = law.position
    c = lang == "c"
    lines = [f"Generated by prsa-ctrl {__version__} (prsa_ctrl.io.codegen) for plant '{inert_text(law.plant)}' "
             "(plant name made inert: non-printable, non-ASCII and comment/string delimiter characters written as "
             "\\u{hex}): the complete discrete controller of the sampled drive, the same per-sample law as the "
             "toolkit's simulator.",
             (f"Call step() every Ts = {iec_real(law.ts)} s (fixed), after init()." if c else
              f"Call the block every Ts = {iec_real(law.ts)} s (a cyclic task of that period), once with Reset := TRUE "
              "first.") + " Units: SI (rad, rad/s, N m, m, m/s, m/s^2).",
             "Per sample: wrap-safe encoder difference in counts -> speed filter (a) -> speed-measurement biquads -> "
             + ("position loop (Kv, integral, velocity and acceleration feed-forward) -> " if p else "")
             + "speed PI with back-calculation anti-windup (k_aw = ki/kp) -> torque limits -> torque-command "
               "biquads -> torque limits.",
             ("Returned: " if c else "TorqueCmd: ") + (
                 "the command computed at the previous call (one-sample computation delay: write it to the current "
                 "loop at the start of the sample)." if law.delay_samples else
                 "the command computed now (no computation delay)."),
             f"Biquads: y = b0 x + b1 x1 + b2 x2 - a1 y1 - a2 y2 (direct form I), {len(law.speed_biquads)} on the "
             f"speed, {len(law.torque_biquads)} on the torque command.",
             "Encoder counts: 32-bit (INTEGER32 0x6064 / DINT / uint32) wired directly; differences are wrap-safe: "
             "count modulus 0 = a counter wrapping at 2^32 (multi-turn, also a signed INTEGER32 crossing 2^31), N > 0 = "
             "a single-turn counter in [0, N) (N = counts per revolution, e.g. 1048576 for 20 bits); the speed must "
             "stay below N/2 counts per sample, and the position (cascade) is accumulated in 32 bits: within "
             "+-2^31 counts of the start.",
             "Faults: a non-finite real input (NaN, inf) or a non-finite result (bad parameters) skips the sample: no "
             "state changes (the integral is not latched), the output holds the last returned command (finite, within "
             "the limits when it was computed), and bit 1 (input) / 2 (result) / 4 (torque_min > torque_max) of the "
             "sticky fault word is set; init clears it.",
             "Enable false: output 0 N m, integral, torque-filter and position-loop states reset to 0 (the speed "
             "measurement keeps tracking; also on a faulted sample); hold true: the speed and position integrals are "
             "frozen.",
             f"States below {iec_real(FLUSH)} in magnitude (speed filter, derivative, biquad outputs) are flushed to 0: "
             "no subnormal numbers at rest; kd = 0 skips the derivative path."]
    if p and p.friction is not None:
        lines.append("Friction feed-forward from the reference speed w = vel_ref/lead (the plant's sliding friction): "
                     "w > 0: g (cp + sp exp(-(w/ws)^2) + vp w); w < 0: -g (cn + sn exp(-(w/ws)^2) - vn w); w = 0: 0; "
                     "added to the acceleration feed-forward.")
    if p:
        lines.append(f"Position loop: measured {p.measured}, every {p.rate} sample(s) (position-loop sample time "
                     f"{p.rate * law.ts:g} s over the speed loop's {law.ts:g} s; position_rate in the parameters"
                     + (f"; its outputs applied {p.delay} position-loop sample(s) after they are computed: its "
                        "computation delay, built into the code" if p.delay else "") + "); "
                     + ("position counts are the encoder counts" if p.measured == "nut_angle"
                        else f"position counts of the linear scale ({iec_real(p.per_count)} m each)")
                     + "; references in m, m/s, m/s^2 of screw travel from the position at init. Resolution: the "
                       "position error is formed in the real type: float (REAL) keeps 24 bits, i.e. an error of "
                       "up to 2^-24 of the travel from the start (81 counts at 1 m for a 20-bit encoder on a 2 mm "
                       "lead); use double (LREAL) for long travel.")
    lines.append("Plant and drive assumptions of these gains:")
    lines += ["  " + s for s in assumption_lines(law)]
    if c:
        lines.append("Compile without floating-point contraction (-ffp-contract=off) and without -ffast-math (the "
                     "NaN checks need IEEE comparisons) to reproduce the toolkit's round-off; the source includes "
                     "<math.h> (exp, tan; expf, tanf in the float build: link with -lm).")
    return lines


def _c_comment(lines: Iterable[str]) -> list[str]:
    out = ["/*"]
    for s in lines:
        s = s.replace("*/", "*\\u{2f}").replace("/*", "\\u{2f}*")  # already inert; belt and braces
        out.append(" * " + s)
    return out + [" */"]


def _st_comment(s: str) -> str:
    return "(* " + s.replace("(*", "(\\u{2a}").replace("*)", "\\u{2a})") + " *)"


#: Marks the enable check in :func:`state_moves` (a disabled drive keeps the speed states and
#: stops before the controller's states move).
ENABLE_GATE = ("enable",)


def state_moves(ns: int, nt: int, position_delay: int | None, delay_samples: int) -> list:
    """The commit of one sample, written once for both emitters (C and Structured Text): a list
    of lines, each a tuple of ``(state, value)`` moves in order, and :data:`ENABLE_GATE` where a
    disabled drive returns. Names are neutral (``S.`` a state, ``O.`` an output, ``T.`` a value
    of this sample; ``sf0.x1`` the first speed filter's last input): :func:`_c_name` and
    :func:`_st_name` spell them in each language.

    Parameters
    ----------
    ns, nt : int
        Speed-measurement and torque-command filter sections.
    position_delay : int or None
        The position loop's computation delay in its samples (None: no position loop).
    delay_samples : int
        The torque command's delay, 0 or 1 controller samples.
    """
    def shift(bank: str, i: int, new: str, out: str) -> tuple:
        f = f"S.{bank}{i}"
        return ((f"{f}.x2", f"{f}.x1"), (f"{f}.x1", new), (f"{f}.y2", f"{f}.y1"), (f"{f}.y1", out))

    lines: list = [(("S.w_filt", "T.wf"),)]
    lines += [shift("sf", i, "T.wf" if i == 0 else f"T.sy{i - 1}", f"T.sy{i}") for i in range(ns)]
    lines += [(("S.deriv", "T.d"),), (("S.w_prev", "T.w"),), (("O.speed", "T.w"),), ENABLE_GATE,
              (("S.integral", "T.integral"),)]
    lines += [shift("tf", i, "T.us" if i == 0 else f"T.ty{i - 1}", f"T.ty{i}") for i in range(nt)]
    if position_delay is not None:
        lines += [((f"S.{k}", f"T.{k}"),) for k in ("phase", "p_integral", "w_ref", "tau_p")]
        lines += [((f"S.pend_w{i}", f"T.pw{i}"), (f"S.pend_t{i}", f"T.pt{i}")) for i in range(1, position_delay + 1)]
    lines += [(("O.command_unfiltered", "T.us"),), (("S.u_out", "S.u_pending" if delay_samples else "T.uf"),),
              (("S.u_pending", "T.uf"),)]
    return lines


#: Filter-state slots: C's ``s->sf[i][k]`` index and ST's ``s_SFi_K`` suffix.
_SLOT = {"x1": (0, "X1"), "x2": (1, "X2"), "y1": (2, "Y1"), "y2": (3, "Y2")}
#: ST spelling of the neutral names of :func:`state_moves` (states, outputs, this sample's values).
_ST_NAMES = {"S.w_filt": "s_WFilt", "S.deriv": "s_Deriv", "S.w_prev": "s_WPrev", "O.speed": "Speed",
             "S.integral": "s_Integral", "S.phase": "s_Phase", "S.p_integral": "s_PIntegral", "S.w_ref": "s_WRef",
             "S.tau_p": "s_TauP", "O.command_unfiltered": "CommandUnfiltered", "S.u_out": "s_UOut",
             "S.u_pending": "s_UPending", "T.wf": "t_Wf", "T.d": "t_Dv", "T.w": "t_W", "T.integral": "t_Int",
             "T.us": "t_Us", "T.uf": "t_Uf", "T.phase": "t_Phase", "T.p_integral": "t_PIntegral", "T.w_ref": "t_WRef",
             "T.tau_p": "t_TauP"}


def _c_name(x: str) -> str:
    """C spelling of a :func:`state_moves` name (``S.sf0.x1`` -> ``s->sf[0][0]``, ``T.sy1`` -> ``sy[1]``)."""
    kind, _, rest = x.partition(".")
    m = re.fullmatch(r"(sf|tf)(\d+)\.(x1|x2|y1|y2)", rest)
    if m:
        return f"s->{m[1]}[{m[2]}][{_SLOT[m[3]][0]}]"
    if kind in ("S", "O"):
        return f"s->{rest}"
    m = re.fullmatch(r"(sy|ty)(\d+)", rest)
    return f"{m[1]}[{m[2]}]" if m else rest


def _st_name(x: str) -> str:
    """ST spelling of a :func:`state_moves` name (``S.sf0.x1`` -> ``s_SF0_X1``, ``T.pw2`` -> ``t_PendW2``)."""
    if x in _ST_NAMES:
        return _ST_NAMES[x]
    kind, _, rest = x.partition(".")
    m = re.fullmatch(r"(sf|tf)(\d+)\.(x1|x2|y1|y2)", rest)
    if m:
        return f"s_{m[1].upper()}{m[2]}_{_SLOT[m[3]][1]}"
    m = re.fullmatch(r"(sy|ty)(\d+)", rest)
    if m:
        return f"t_{'SF' if m[1] == 'sy' else 'TF'}{m[2]}"
    m = re.fullmatch(r"(pend_w|pend_t|pw|pt)(\d+)", rest)
    if m:
        return f"{'s' if kind == 'S' else 't'}_Pend{'W' if m[1][-1] == 'w' else 'T'}{m[2]}"
    raise KeyError(x)


def c_code(law: "DriveLaw", *, name: str = "prsa_ctrl", real: str = "double", header: str | None = None,
           differences: str = "counts") -> tuple[str, str]:
    """The law as C99 for firmware: ``(header text, source text)``.

    The header (``extern "C"`` guarded) declares ``<name>_real`` (``float`` or ``double``),
    the run-time parameter struct ``<name>_params`` (gains, limits, filter coefficients: all
    changeable between two steps), the physical values ``<name>_physical`` they are computed
    from, the state ``<name>_state`` and::

        void <name>_params_default(<name>_params *p);                     the exported values
        void <name>_physical_default(<name>_physical *ph);                the exported physical values
        int  <name>_params_compute(<name>_params *p, const <name>_physical *ph);   0: done; < 0: refused, p unchanged
        void <name>_init(const <name>_params *p, <name>_state *s, uint32_t count_prev, <name>_real speed0,
                         <name>_real integral0, <name>_real torque0[, uint32_t position_count]);
        <name>_real <name>_step(const <name>_params *p, <name>_state *s, uint32_t count, <name>_real speed_ref,
                                int enable, int hold);                                         speed loop
        <name>_real <name>_step(const <name>_params *p, <name>_state *s, uint32_t count, <name>_real pos_ref,
                                <name>_real vel_ref, <name>_real acc_ref[, uint32_t position_count],
                                int enable, int hold);                                         cascade

    ``count`` (and ``position_count`` with a linear scale) are raw 32-bit counters: wrap-safe
    differences (see the header). Float builds use float arithmetic only (``expf``, no 64-bit
    integers). No library beyond ``<stdint.h>`` and ``<math.h>``.

    Parameters
    ----------
    law : DriveLaw
    name : str
        Prefix of every identifier (also of the internal functions: unity builds).
    real : {"double", "float"}
    header : str, optional
        File name the source includes (default ``<name>.h``).
    differences : {"counts"}
        Speed and position differences in integer counts (kept for compatibility).

    Returns
    -------
    tuple of str
    """
    if not isinstance(law, DriveLaw):
        raise ValueError(f"law = {law!r}; expected a DriveLaw (see drive_law)")
    n, real = _check_name(name), _check_real(real)
    _check_differences(differences)
    header = header or f"{n}.h"
    check_header_name(header)
    fl = real == "float"
    R = f"{n}_real"
    U = n.upper()
    p = law.position
    ns, nt = len(law.speed_biquads), len(law.torque_biquads)
    scale = p is not None and p.measured != "nut_angle"
    fric = p is not None and p.friction is not None
    math_fn = (lambda f: f + "f") if fl else (lambda f: f)
    consts = law_constants(law)
    ref_args = f"{R} speed_ref" if p is None else f"{R} pos_ref, {R} vel_ref, {R} acc_ref"
    step_args = f"uint32_t count, {ref_args}" + (", uint32_t position_count" if scale else "") + ", int enable, int hold"
    init_args = f"uint32_t count_prev, {R} speed0, {R} integral0, {R} torque0" + (
        ", uint32_t position_count" if scale else "")
    guard = f"{U}_H"
    # ---- header
    h = [*_c_comment(_header_comment(law, "c")), f"#ifndef {guard}", f"#define {guard}", "",
         "#include <stdint.h>", "", "#ifdef __cplusplus", 'extern "C" {', "#endif", "",
         f"typedef {real} {R};", "",
         f"#define {U}_FAULT_INPUT 1u   /* a non-finite real input: the sample was skipped */",
         f"#define {U}_FAULT_RESULT 2u  /* a non-finite result (parameters): the sample was skipped */",
         f"#define {U}_FAULT_LIMITS 4u  /* torque_min > torque_max: the sample was skipped */",
         f"#define {U}_SPEED_BIQUADS {ns}", f"#define {U}_TORQUE_BIQUADS {nt}", "",
         "/* Run-time parameters: change any field between two steps (retuning needs no rebuild). */",
         "typedef struct {"]
    for cname, _, comment in consts:
        h.append(f"    {R} {cname}; /* {comment} */")
    h += ["    uint32_t count_modulus; /* 0: the encoder counter wraps at 2^32; N > 0: single-turn counts in [0, N) */"]
    if scale:
        h.append("    uint32_t position_modulus; /* the same for the linear scale's counter (0: wraps at 2^32) */")
    if p is not None:
        h.append("    int32_t position_rate; /* position-loop sample time in samples (>= 1) */")
    h += [f"}} {n}_params;", "",
          "/* Physical values the parameters are computed from (SI; <name>_params_compute). */",
          "typedef struct {",
          f"    {R} ts_s;                 /* sample time, s */",
          f"    {R} torque_max_n_m, torque_min_n_m; /* torque limits, N m */",
          "    uint32_t counts_per_rev;    /* encoder counts per revolution */",
          "    uint32_t count_modulus;     /* see the parameters */",
          f"    {R} speed_filter_tau_s;   /* speed-measurement low-pass time constant, s */",
          f"    {R} kp, ki, kd, tf_s;     /* speed PI(D): N m s/rad, N m/rad, N m s^2/rad, s */",
          f"    {R} setpoint_weight, torque_ff_n_m;"]
    for pl, cnt in (("sf", ns), ("tf", nt)):
        if cnt:
            h.append(f"    struct {{ int tustin; {R} num[3], den[3], prewarp_hz, coef[5]; }} {pl}[{cnt}]; "
                     f"/* {'speed-measurement' if pl == 'sf' else 'torque-command'} filters: H(s) = (n2 s^2 + n1 s + "
                     "n0)/(d2 s^2 + d1 s + d0); tustin: Tustin prewarped at prewarp_hz (0: 2/Ts), else coef "
                     "(b0 b1 b2 a1 a2) as given */")
    if p is not None:
        h += [f"    {R} kv_per_s, ki_per_s2, kvff, kaff, inertia_kg_m2, lead_m_per_rad, unit_m, err_to_rad, "
              "pos_per_count;", "    int32_t position_rate;"]
        if scale:
            h.append("    uint32_t position_modulus;")
        if fric:
            h.append(f"    {R} friction[8]; /* cp, cn, sp, sn, ws, vp, vn, g */")
    h += [f"}} {n}_physical;", "", "/* State: owned by the caller, one per axis; no static data in the code. */",
          "typedef struct {",
          "    uint32_t count_prev;     /* encoder count at the previous sample (raw) */",
          f"    {R} w_filt;            /* drive speed filter output, rad/s */",
          f"    {R} w_prev;            /* speed the PI used at the previous sample, rad/s */",
          f"    {R} deriv;             /* filtered derivative of the speed, rad/s^2 */",
          f"    {R} integral;          /* PI integral, N m */",
          f"    {R} u_pending;         /* command computed at the previous sample, N m */",
          f"    {R} u_out;             /* command returned last, N m (held on a faulted sample) */"]
    if ns:
        h.append(f"    {R} sf[{ns}][4];          /* speed-measurement biquads: x1, x2, y1, y2 */")
    if nt:
        h.append(f"    {R} tf[{nt}][4];          /* torque-command biquads: x1, x2, y1, y2 */")
    if p is not None:
        h += ["    uint32_t travel;        /* position counts since init (two's complement) */",
              *(["    uint32_t position_prev; /* linear-scale count at the previous sample (raw) */"] if scale else []),
              "    int32_t phase;          /* samples since the last position-loop sample */",
              f"    {R} p_integral;        /* position-loop integral, rad/s */",
              f"    {R} w_ref;             /* speed reference, held between position samples, rad/s */",
              f"    {R} tau_p;             /* feed-forward torque, held, N m */"]
        for i in range(1, p.delay + 1):
            h.append(f"    {R} pend_w{i}, pend_t{i}; /* position-loop output {i} position samples old (delay {p.delay}): "
                     "speed reference rad/s, feed-forward N m */")
    h += [f"    {R} speed;             /* diagnostics: filtered speed of this sample, rad/s */",
          f"    {R} command_unfiltered; /* diagnostics: limited PI command before the torque filters, N m */",
          "    uint32_t fault;         /* sticky fault bits (see *_FAULT_*); cleared by init */",
          f"}} {n}_state;", "",
          f"void {n}_params_default({n}_params *p);",
          f"void {n}_physical_default({n}_physical *ph);",
          f"/* 0: p computed from ph; < 0: ph refused (non-finite, ts, tf, tau or a filter frequency out of range), "
          "p unchanged. */",
          f"int {n}_params_compute({n}_params *p, const {n}_physical *ph);", "",
          "/* Initialise at a steady state: previous encoder count (raw), speed (rad/s), PI integral (N m), the "
          "command being applied (N m)" + (", and the linear scale's count now" if scale else "")
          + ". The position reference (0 m) starts here. At rest: count_prev = the count now, speed0 = 0, "
            "integral0 = torque0 = the holding torque. */",
          f"void {n}_init(const {n}_params *p, {n}_state *s, {init_args});", "",
          "/* One sample; returns the torque command (N m). " + (
              "speed_ref in rad/s of the motor." if p is None else
              "pos_ref (m), vel_ref (m/s), acc_ref (m/s^2) of screw travel.")
          + " enable = 0: output 0 (see above); hold != 0: integrals frozen. */",
          f"{R} {n}_step(const {n}_params *p, {n}_state *s, {step_args});", "",
          "#ifdef __cplusplus", "}", "#endif", "", f"#endif /* {guard} */", ""]
    # ---- source
    z = f"({R})0"
    c = [*_c_comment(_header_comment(law, "c")), f'#include "{header}"', *(["#include <math.h>"]), ""]
    c += [f"void {n}_params_default({n}_params *p)", "{"]
    for cname, v, _ in consts:
        c.append(f"    p->{cname} = ({R}){_lit(v)};")
    c.append("    p->count_modulus = 0u;")
    if scale:
        c.append("    p->position_modulus = 0u;")
    if p is not None:
        c.append(f"    p->position_rate = {int(p.rate)};")
    c += ["}", "", f"void {n}_physical_default({n}_physical *ph)", "{",
          f"    ph->ts_s = ({R}){_lit(law.ts)};",
          f"    ph->torque_max_n_m = ({R}){_lit(law.torque_limit_n_m)};",
          f"    ph->torque_min_n_m = ({R}){_lit(-law.torque_limit_n_m)};",
          f"    ph->counts_per_rev = {int(round(2 * math.pi / law.rad_per_count))}u;",
          "    ph->count_modulus = 0u;",
          f"    ph->speed_filter_tau_s = ({R}){_lit(-law.ts / math.log(law.speed_filter_a))};",
          f"    ph->kp = ({R}){_lit(law.kp)};", f"    ph->ki = ({R}){_lit(law.ki)};",
          f"    ph->kd = ({R}){_lit(law.kd)};", f"    ph->tf_s = ({R}){_lit(law.tf)};",
          f"    ph->setpoint_weight = ({R}){_lit(law.setpoint_weight)};",
          f"    ph->torque_ff_n_m = ({R}){_lit(law.torque_ff_n_m)};"]
    for pl, bqs, specs in (("sf", law.speed_biquads, law.speed_filter_specs), ("tf", law.torque_biquads,
                                                                                law.torque_filter_specs)):
        for i, b in enumerate(bqs):
            sp = specs[i] if i < len(specs) else None
            c.append(f"    ph->{pl}[{i}].tustin = {1 if sp is not None and sp.tustin else 0};")
            for k in range(3):
                c.append(f"    ph->{pl}[{i}].num[{k}] = ({R}){_lit(sp.num[k] if sp else 0.0)}; "
                         f"ph->{pl}[{i}].den[{k}] = ({R}){_lit(sp.den[k] if sp else 0.0)};")
            c.append(f"    ph->{pl}[{i}].prewarp_hz = ({R}){_lit(sp.prewarp_hz if sp else 0.0)};")
            for k in range(5):
                c.append(f"    ph->{pl}[{i}].coef[{k}] = ({R}){_lit(b[k])};")
    if p is not None:
        for f_, v in (("kv_per_s", p.kv), ("ki_per_s2", p.ki), ("kvff", p.kvff), ("kaff", p.kaff),
                      ("inertia_kg_m2", p.inertia_kg_m2), ("lead_m_per_rad", p.lead_m_per_rad), ("unit_m", p.unit_m),
                      ("err_to_rad", p.err_to_rad), ("pos_per_count", p.per_count)):
            c.append(f"    ph->{f_} = ({R}){_lit(v)};")
        c.append(f"    ph->position_rate = {int(p.rate)};")
        if scale:
            c.append("    ph->position_modulus = 0u;")
        if fric:
            for k, v in enumerate(p.friction):
                c.append(f"    ph->friction[{k}] = ({R}){_lit(v)};")
    tustin_fn = [f"/* Tustin biquad of (n2 s^2 + n1 s + n0)/(d2 s^2 + d1 s + d0), K = w0/tan(w0 ts/2) (w0 > 0) or 2/ts. */",
          f"static int {n}_tustin_(const {R} *num, const {R} *den, {R} prewarp_hz, {R} ts, {R} *out)", "{",
          f"    {R} k, kk, a0, b[3], a[3];", "    int i;",
          f"    if (prewarp_hz > {z}) {{",
          f"        {R} w0 = ({R}){_lit(2 * math.pi)} * prewarp_hz;",
          f"        if (!(w0 * ts < ({R}){_lit(math.pi)})) return -1;  /* at or above Nyquist */",
          f"        k = w0 / {math_fn('tan')}(w0 * ts / ({R})2);",
          f"    }} else {{", f"        k = ({R})2 / ts;", "    }",
          "    kk = k * k;",
          f"    if (den[0] != {z}) {{  /* second order */",
          f"        b[0] = num[0] * kk + num[1] * k + num[2]; b[1] = ({R})2 * (num[2] - num[0] * kk); "
          "b[2] = num[0] * kk - num[1] * k + num[2];",
          f"        a[0] = den[0] * kk + den[1] * k + den[2]; a[1] = ({R})2 * (den[2] - den[0] * kk); "
          "a[2] = den[0] * kk - den[1] * k + den[2];",
          "    } else {  /* first order: (n1 s + n0)/(d1 s + d0) */",
          f"        b[0] = num[1] * k + num[2]; b[1] = num[2] - num[1] * k; b[2] = {z};",
          f"        a[0] = den[1] * k + den[2]; a[1] = den[2] - den[1] * k; a[2] = {z};",
          "    }",
          f"    if (!{n}_finite_(a[0]) || a[0] == {z}) return -1;",
          "    a0 = a[0];",
          "    for (i = 0; i < 3; i++) out[i] = b[i] / a0;",
          "    out[3] = a[1] / a0; out[4] = a[2] / a0;",
          f"    for (i = 0; i < 5; i++) if (!{n}_finite_(out[i])) return -1;",
          "    return 0;", "}", ""]
    c += ["}", "",
          f"static int {n}_finite_({R} x) {{ return (x - x) == {z}; }}  /* false for NaN and +-inf */", "",
          f"static {R} {n}_flush_({R} x) {{ return (x < ({R}){_lit(FLUSH)} && x > -({R}){_lit(FLUSH)}) ? {z} : x; }}", "",
          *(tustin_fn if ns or nt else []),
          f"int {n}_params_compute({n}_params *p, const {n}_physical *ph)", "{",
          f"    {n}_params q = *p;", *(["    int i;"] if ns or nt else []),
          f"    if (!({n}_finite_(ph->ts_s) && ph->ts_s > {z} && {n}_finite_(ph->speed_filter_tau_s) && "
          f"ph->speed_filter_tau_s > {z} && {n}_finite_(ph->tf_s) && ph->tf_s > {z})) return -1;",
          f"    if (!({n}_finite_(ph->kp) && ph->kp >= {z} && {n}_finite_(ph->ki) && ph->ki >= {z} && "
          f"{n}_finite_(ph->kd) && ph->kd >= {z})) return -2;",
          f"    if (!({n}_finite_(ph->torque_max_n_m) && {n}_finite_(ph->torque_min_n_m) && "
          f"ph->torque_min_n_m <= ph->torque_max_n_m) || ph->counts_per_rev == 0u) return -3;",
          f"    if (!({n}_finite_(ph->setpoint_weight) && {n}_finite_(ph->torque_ff_n_m))) return -3;",
          "    q.ts = ph->ts_s;", "    q.torque_max = ph->torque_max_n_m;", "    q.torque_min = ph->torque_min_n_m;",
          f"    q.rad_per_count = ({R}){_lit(2 * math.pi)} / ({R})ph->counts_per_rev;",
          "    q.count_modulus = ph->count_modulus;",
          f"    q.a_w = {math_fn('exp')}(-ph->ts_s / ph->speed_filter_tau_s);",
          f"    q.one_minus_a_w = ({R})1 - q.a_w;",
          "    q.kp = ph->kp;", "    q.ki = ph->ki;", "    q.kd = ph->kd;", "    q.b_sp = ph->setpoint_weight;",
          f"    q.beta = {math_fn('exp')}(-ph->ts_s / ph->tf_s);", f"    q.one_minus_beta = ({R})1 - q.beta;",
          f"    q.k_aw = ph->ki / (ph->kp > ({R}){_lit(1e-9)} ? ph->kp : ({R}){_lit(1e-9)});",
          "    q.tau_ff = ph->torque_ff_n_m;"]
    for pl, cnt in (("sf", ns), ("tf", nt)):
        for i in range(cnt):
            c += ["    {", f"        {R} co[5];",
                  f"        if (ph->{pl}[{i}].tustin) {{",
                  f"            if ({n}_tustin_(ph->{pl}[{i}].num, ph->{pl}[{i}].den, ph->{pl}[{i}].prewarp_hz, "
                  f"ph->ts_s, co) != 0) return -4;",
                  "        } else {",
                  f"            for (i = 0; i < 5; i++) co[i] = ph->{pl}[{i}].coef[i];",
                  "        }",
                  f"        q.{pl}{i}_b0 = co[0]; q.{pl}{i}_b1 = co[1]; q.{pl}{i}_b2 = co[2]; "
                  f"q.{pl}{i}_a1 = co[3]; q.{pl}{i}_a2 = co[4];", "    }"]
    if p is not None:
        c += [f"    if (ph->position_rate < 1 || !({n}_finite_(ph->lead_m_per_rad) && ph->lead_m_per_rad > {z} && "
              f"{n}_finite_(ph->unit_m) && ph->unit_m > {z} && {n}_finite_(ph->inertia_kg_m2))) return -5;",
              f"    q.tp_kip = (({R})ph->position_rate * ph->ts_s) * ph->ki_per_s2;", "    q.kv = ph->kv_per_s;",
              "    q.kvff = ph->kvff;", "    q.kaff_j = ph->kaff * ph->inertia_kg_m2;", "    q.lead = ph->lead_m_per_rad;",
              "    q.unit_m = ph->unit_m;", "    q.err_to_rad = ph->err_to_rad;", "    q.pos_per_count = ph->pos_per_count;",
              "    q.position_rate = ph->position_rate;"]
        if scale:
            c.append("    q.position_modulus = ph->position_modulus;")
        if fric:
            c += [f"    q.fr_{k} = ph->friction[{i}];" for i, k in enumerate(("cp", "cn", "sp", "sn", "ws", "vp", "vn", "g"))]
    c += ["    *p = q;", "    return 0;", "}", "",
          "/* Signed difference of two raw counts, wrap-safe: modulus 0 = 2^32, else counts in [0, modulus). */",
          f"static int32_t {n}_delta_(uint32_t now, uint32_t prev, uint32_t modulus)", "{",
          "    uint32_t d;", "    if (modulus == 0u) {", "        d = now - prev;",
          "        return d < 0x80000000u ? (int32_t)d : -(int32_t)(0xFFFFFFFFu - d) - 1;", "    }",
          "    now %= modulus;", "    prev %= modulus;", "    d = now >= prev ? now - prev : modulus - (prev - now);",
          "    return d <= modulus / 2u ? (int32_t)d : -(int32_t)(modulus - d);", "}", ""]
    if p is not None:
        c += ["/* Two's complement value of a uint32 (portable). */",
              f"static int32_t {n}_signed_(uint32_t u)",
              "{", "    return u < 0x80000000u ? (int32_t)u : -(int32_t)(0xFFFFFFFFu - u) - 1;", "}", ""]
    if fric:
        c += [f"static {R} {n}_friction_(const {n}_params *p, {R} w)", "{", f"    {R} x = w / p->fr_ws;",
              f"    {R} shape = {math_fn('exp')}(-(x * x));",
              f"    if (w > {z}) return p->fr_g * (p->fr_cp + p->fr_sp * shape + p->fr_vp * w);",
              f"    if (w < {z}) return p->fr_g * -(p->fr_cn + p->fr_sn * shape - p->fr_vn * w);", f"    return {z};",
              "}", ""]
    c += ["/* Drive disabled: output 0, integrals, torque filters and the position loop reset. */",
          f"static void {n}_off_({n}_state *s)", "{", f"    s->integral = {z};", f"    s->u_pending = {z};",
          f"    s->u_out = {z};", f"    s->command_unfiltered = {z};"]
    for i in range(nt):
        c.append(f"    s->tf[{i}][0] = s->tf[{i}][1] = s->tf[{i}][2] = s->tf[{i}][3] = {z};")
    if p is not None:
        c += ["    s->phase = 0;", f"    s->p_integral = {z};", f"    s->w_ref = {z};", f"    s->tau_p = {z};"]
        c += [f"    s->pend_w{i} = {z}; s->pend_t{i} = {z};" for i in range(1, p.delay + 1)]
    c += ["}", ""]
    c += [f"void {n}_init(const {n}_params *p, {n}_state *s, {init_args})", "{",
          "    (void)p;", "    s->count_prev = count_prev;", "    s->w_filt = speed0;", "    s->w_prev = speed0;",
          f"    s->deriv = {z};", "    s->integral = integral0;", "    s->u_pending = torque0;", "    s->u_out = torque0;",
          "    s->speed = speed0;", "    s->command_unfiltered = torque0;", "    s->fault = 0u;"]
    for i in range(ns):
        c.append(f"    s->sf[{i}][0] = s->sf[{i}][1] = s->sf[{i}][2] = s->sf[{i}][3] = speed0;")
    for i in range(nt):
        c.append(f"    s->tf[{i}][0] = s->tf[{i}][1] = s->tf[{i}][2] = s->tf[{i}][3] = torque0;")
    if p is not None:
        c += ["    s->travel = 0u;", *(["    s->position_prev = position_count;"] if scale else []), "    s->phase = 0;",
              f"    s->p_integral = {z};", f"    s->w_ref = {z};", f"    s->tau_p = {z};"]
        c += [f"    s->pend_w{i} = {z}; s->pend_t{i} = {z};" for i in range(1, p.delay + 1)]
    c += ["}", "", f"{R} {n}_step(const {n}_params *p, {n}_state *s, {step_args})", "{",
          f"    {R} w, wf, d, e, u, us, uf, ref, tau_ff, integral;", *([f"    {R} y;"] if ns or nt else []),
          *([f"    {R} sy[{ns}];"] if ns else []), *([f"    {R} ty[{nt}];"] if nt else []),
          *([f"    {R} p_integral = s->p_integral, w_ref = s->w_ref, tau_p = s->tau_p;",
             "    int32_t phase = s->phase;"] if p is not None else []),
          *([f"    {R} " + ", ".join(f"pw{i} = s->pend_w{i}, pt{i} = s->pend_t{i}" for i in range(1, p.delay + 1)) + ";"]
            if p is not None and p.delay else []),
          f"    int32_t dn = {n}_delta_(count, s->count_prev, p->count_modulus);",
          *([f"    int32_t dp = {n}_delta_(position_count, s->position_prev, p->position_modulus);"] if scale else []),
          "    s->count_prev = count;  /* integers: always valid */"]
    if p is not None:
        c += [f"    s->travel = s->travel + (uint32_t){'dp' if scale else 'dn'};"]
        if scale:
            c.append("    s->position_prev = position_count;")
    fin = [f"{n}_finite_({x})" for x in (["speed_ref"] if p is None else ["pos_ref", "vel_ref", "acc_ref"])]
    off = f"        if (!enable) {n}_off_(s);"
    c += [f"    if (!({' && '.join(fin)})) {{", f"        s->fault |= {U}_FAULT_INPUT;", off, "        return s->u_out;", "    }",
          "    if (!(p->torque_min <= p->torque_max)) {", f"        s->fault |= {U}_FAULT_LIMITS;", off, "        return s->u_out;",
          "    }",
          "    /* speed: encoder difference in counts (wrap-safe), drive speed filter */",
          f"    wf = {n}_flush_(p->a_w * s->w_filt + p->one_minus_a_w * (({R})dn * p->rad_per_count) / p->ts);",
          "    w = wf;"]
    for i in range(ns):
        c += [f"    y = p->sf{i}_b0 * w + p->sf{i}_b1 * s->sf[{i}][0] + p->sf{i}_b2 * s->sf[{i}][1] - p->sf{i}_a1 * "
              f"s->sf[{i}][2] - p->sf{i}_a2 * s->sf[{i}][3];", f"    sy[{i}] = {n}_flush_(y);", f"    w = sy[{i}];"]
    c += [f"    if (p->kd != {z}) {{",
          f"        d = {n}_flush_(p->beta * s->deriv + p->one_minus_beta * (w - s->w_prev) / p->ts);",
          f"    }} else {{", f"        d = {z};  /* no derivative path: nothing decays into subnormals */", "    }"]
    if p is None:
        c += ["    ref = speed_ref;", "    tau_ff = p->tau_ff;"]
    else:
        c += ["    if (phase == 0) {  /* position-loop sample */",
              f"        {R} ep = (pos_ref / p->unit_m - ({R}){n}_signed_(s->travel) * p->pos_per_count) * p->err_to_rad;",
              "        if (!hold) p_integral = p_integral + p->tp_kip * ep;",
              "        w_ref = p->kv * ep + p_integral + p->kvff * vel_ref / p->lead;",
              "        tau_p = p->kaff_j * acc_ref / p->lead" + (f" + {n}_friction_(p, vel_ref / p->lead);" if fric else ";"),
              *([f"        /* computation delay of {p.delay} position sample(s): the oldest pending output is "
                 "applied */"] + [f"        {{ {R} wn = w_ref, tn = tau_p;", f"        w_ref = pw{p.delay}; "
                                  f"tau_p = pt{p.delay};"]
                + [f"        pw{i} = pw{i - 1}; pt{i} = pt{i - 1};" for i in range(p.delay, 1, -1)]
                + ["        pw1 = wn; pt1 = tn; }"] if p.delay else []),
              "    }", "    phase = phase + 1 >= p->position_rate ? 0 : phase + 1;",
              "    ref = w_ref;", "    tau_ff = p->tau_ff + tau_p;"]
    c += ["    e = ref - w;", "    u = p->kp * (p->b_sp * ref - w) + s->integral - p->kd * d + tau_ff;",
          "    us = u > p->torque_max ? p->torque_max : (u < p->torque_min ? p->torque_min : u);",
          "    integral = hold ? s->integral : s->integral + p->ts * (p->ki * e + p->k_aw * (us - u));", "    uf = us;"]
    for i in range(nt):
        c += [f"    y = p->tf{i}_b0 * uf + p->tf{i}_b1 * s->tf[{i}][0] + p->tf{i}_b2 * s->tf[{i}][1] - p->tf{i}_a1 * "
              f"s->tf[{i}][2] - p->tf{i}_a2 * s->tf[{i}][3];", f"    ty[{i}] = {n}_flush_(y);", f"    uf = ty[{i}];"]
    if nt:
        c.append("    uf = uf > p->torque_max ? p->torque_max : (uf < p->torque_min ? p->torque_min : uf);")
    c += [f"    if (!({n}_finite_(u) && {n}_finite_(uf) && {n}_finite_(integral))) {{",
          f"        s->fault |= {U}_FAULT_RESULT;", off, "        return s->u_out;", "    }",
          "    /* commit */"]
    for line in state_moves(ns, nt, None if p is None else p.delay, law.delay_samples):
        if line is ENABLE_GATE:
            c += ["    if (!enable) {", f"        {n}_off_(s);", "        return s->u_out;", "    }"]
        else:
            c.append("    " + " ".join(f"{_c_name(dst)} = {_c_name(src)};" for dst, src in line))
    c += ["    return s->u_out;", "}", ""]
    return "\n".join(h), "\n".join(c)


def _st_delta(now: str, prev: str, modulus: str, out: str) -> list[str]:
    """ST lines: ``out`` (DINT) := wrap-safe difference of the raw counts ``now`` (DINT input) and
    ``prev`` (UDINT state), as the C ``*_delta_``."""
    return [f"t_Now := DINT_TO_UDINT({now});", f"t_Prev := {prev};", f"IF {modulus} = 0 THEN",
            "    t_D := t_Now - t_Prev;",
            f"    IF t_D < 16#80000000 THEN {out} := UDINT_TO_DINT(t_D); "
            f"ELSE {out} := -UDINT_TO_DINT(16#FFFFFFFF - t_D) - 1; END_IF;",
            "ELSE", f"    t_Now := t_Now MOD {modulus};", f"    t_Prev := t_Prev MOD {modulus};",
            f"    IF t_Now >= t_Prev THEN t_D := t_Now - t_Prev; ELSE t_D := {modulus} - (t_Prev - t_Now); END_IF;",
            f"    IF t_D <= {modulus} / 2 THEN {out} := UDINT_TO_DINT(t_D); "
            f"ELSE {out} := -UDINT_TO_DINT({modulus} - t_D); END_IF;", "END_IF;"]


def _st_flush(x: str) -> str:
    return f"IF {x} < {iec_real(FLUSH)} AND {x} > -{iec_real(FLUSH)} THEN {x} := 0.0; END_IF;"


def _st_fin(x: str) -> str:
    return f"({x} - {x}) = 0.0"


def st_parts(law: "DriveLaw", *, name: str = "PrsaCtrl", real: str = "double") -> dict[str, Any]:
    """The function block's parts: ``{"name", "comment" (lines), "inputs", "outputs", "locals"
    (each a list of (name, type, initial value or None, comment)), "body" (ST statements)}`` --
    what :func:`st_code` writes as one text."""
    if not isinstance(law, DriveLaw):
        raise ValueError(f"law = {law!r}; expected a DriveLaw (see drive_law)")
    n, R = _check_name(name), REAL_TYPES[_check_real(real)]
    p = law.position
    ns, nt = len(law.speed_biquads), len(law.torque_biquads)
    scale = p is not None and p.measured != "nut_angle"
    fric = p is not None and p.friction is not None
    r0 = "0.0"
    ins: list[tuple[str, str, str | None, str]] = [
        ("Reset", "BOOL", "FALSE", "TRUE: initialise from the Init* inputs"),
        ("Enable", "BOOL", "TRUE", "FALSE: output 0 N m, integrals and torque filters reset"),
        ("Hold", "BOOL", "FALSE", "TRUE: speed and position integrals frozen"),
        ("EncCount", "DINT", "0", "encoder counts, raw 32-bit (e.g. 0x6064 INTEGER32), wrap-safe")]
    if p is None:
        ins.append(("SpeedRef", R, r0, "speed reference, rad/s"))
    else:
        ins += [("PosRef", R, r0, "position reference, m of screw travel from the start"),
                ("VelRef", R, r0, "speed reference, m/s"), ("AccRef", R, r0, "acceleration reference, m/s^2")]
        if scale:
            ins.append(("PosCount", "DINT", "0", "linear-scale counts, raw 32-bit, wrap-safe"))
    ins += [("InitCountPrev", "DINT", "0", "encoder count at the previous sample"),
            ("InitSpeed", R, r0, "rad/s"), ("InitIntegral", R, r0, "N m"),
            ("InitTorque", R, r0, "command being applied, N m")]
    if scale:
        ins.append(("InitPosCount", "DINT", "0", "linear-scale count at Reset"))
    ins.append(("CountModulus", "UDINT", "0", "0: the counter wraps at 2^32; N: single-turn counts in [0, N)"))
    if scale:
        ins.append(("PosModulus", "UDINT", "0", "the same for the linear scale"))
    for cname, v, comment in law_constants(law):
        ins.append((f"P_{cname.upper()}", R, iec_real(v), "parameter: " + comment))
    if p is not None:
        ins.append(("P_POSITION_RATE", "DINT", str(int(p.rate)), "parameter: position-loop sample time in samples"))
    outs = [("TorqueCmd", R, r0, "N m"), ("Speed", R, r0, "filtered speed, rad/s"),
            ("CommandUnfiltered", R, r0, "limited PI command before the torque filters, N m"),
            ("Fault", "DWORD", "0", "sticky fault bits: 1 input, 2 result, 4 limits; Reset clears")]
    loc: list[tuple[str, str, str | None, str]] = [
        ("s_CountPrev", "UDINT", "0", ""), ("s_WFilt", R, r0, ""), ("s_WPrev", R, r0, ""), ("s_Deriv", R, r0, ""),
        ("s_Integral", R, r0, ""), ("s_UPending", R, r0, ""), ("s_UOut", R, r0, ""), ("s_Fault", "DWORD", "0", "")]
    for pl, cnt in (("SF", ns), ("TF", nt)):
        for i in range(cnt):
            loc += [(f"s_{pl}{i}_{k}", R, r0, "") for k in ("X1", "X2", "Y1", "Y2")] + [(f"t_{pl}{i}", R, r0, "")]
    if p is not None:
        loc += [("s_Travel", "UDINT", "0", ""), ("s_Phase", "DINT", "0", ""), ("s_PIntegral", R, r0, ""),
                ("s_WRef", R, r0, ""), ("s_TauP", R, r0, ""), ("t_Ep", R, r0, ""), ("t_PIntegral", R, r0, ""),
                ("t_WRef", R, r0, ""), ("t_TauP", R, r0, ""), ("t_Phase", "DINT", "0", ""), ("t_Trav", "DINT", "0", "")]
        for i in range(1, p.delay + 1):
            loc += [(f"s_PendW{i}", R, r0, ""), (f"s_PendT{i}", R, r0, ""), (f"t_PendW{i}", R, r0, ""),
                    (f"t_PendT{i}", R, r0, "")]
        if p.delay:
            loc += [("t_NewW", R, r0, ""), ("t_NewT", R, r0, "")]
        if scale:
            loc += [("s_PosPrev", "UDINT", "0", ""), ("t_Dp", "DINT", "0", "")]
        if fric:
            loc += [("t_FrW", R, r0, ""), ("t_FrX", R, r0, ""), ("t_TauFr", R, r0, "")]
    loc += [("t_Now", "UDINT", "0", ""), ("t_Prev", "UDINT", "0", ""), ("t_D", "UDINT", "0", ""), ("t_Dn", "DINT", "0", "")]
    loc += [(f"t_{k}", R, r0, "") for k in ("W", "Wf", "Dv", "E", "U", "Us", "Uf", "Y", "Ref", "TauFF", "Int")]
    b = ["IF Reset THEN", "    s_CountPrev := DINT_TO_UDINT(InitCountPrev);", "    s_WFilt := InitSpeed;",
         "    s_WPrev := InitSpeed;", "    s_Deriv := 0.0;", "    s_Integral := InitIntegral;",
         "    s_UPending := InitTorque;", "    s_UOut := InitTorque;", "    s_Fault := 0;"]
    for i in range(ns):
        b.append(f"    s_SF{i}_X1 := InitSpeed; s_SF{i}_X2 := InitSpeed; s_SF{i}_Y1 := InitSpeed; s_SF{i}_Y2 := InitSpeed;")
    for i in range(nt):
        b.append(f"    s_TF{i}_X1 := InitTorque; s_TF{i}_X2 := InitTorque; s_TF{i}_Y1 := InitTorque; "
                 f"s_TF{i}_Y2 := InitTorque;")
    if p is not None:
        b += ["    s_Travel := 0;", *(["    s_PosPrev := DINT_TO_UDINT(InitPosCount);"] if scale else []),
              "    s_Phase := 0;", "    s_PIntegral := 0.0;", "    s_WRef := 0.0;", "    s_TauP := 0.0;"]
        b += [f"    s_PendW{i} := 0.0; s_PendT{i} := 0.0;" for i in range(1, p.delay + 1)]
    b += ["    TorqueCmd := InitTorque;", "    Speed := InitSpeed;", "    CommandUnfiltered := InitTorque;",
          "    Fault := s_Fault;", "    RETURN;", "END_IF;", "",
          "(* wrap-safe encoder difference in counts *)", *_st_delta("EncCount", "s_CountPrev", "CountModulus", "t_Dn"),
          "s_CountPrev := DINT_TO_UDINT(EncCount);"]
    if p is not None:
        if scale:
            b += _st_delta("PosCount", "s_PosPrev", "PosModulus", "t_Dp")
            b += ["s_PosPrev := DINT_TO_UDINT(PosCount);", "s_Travel := s_Travel + DINT_TO_UDINT(t_Dp);"]
        else:
            b.append("s_Travel := s_Travel + DINT_TO_UDINT(t_Dn);")
    fin = " AND ".join(_st_fin(x) for x in (["SpeedRef"] if p is None else ["PosRef", "VelRef", "AccRef"]))
    off = ["s_Integral := 0.0;", "s_UPending := 0.0;", "s_UOut := 0.0;", "CommandUnfiltered := 0.0;"]
    for i in range(nt):
        off.append(f"s_TF{i}_X1 := 0.0; s_TF{i}_X2 := 0.0; s_TF{i}_Y1 := 0.0; s_TF{i}_Y2 := 0.0;")
    if p is not None:
        off += ["s_Phase := 0;", "s_PIntegral := 0.0;", "s_WRef := 0.0;", "s_TauP := 0.0;"]
        off += [f"s_PendW{i} := 0.0; s_PendT{i} := 0.0;" for i in range(1, p.delay + 1)]
    ret = ["    IF NOT Enable THEN", *["        " + x for x in off], "    END_IF;",
           "    TorqueCmd := s_UOut;", "    Fault := s_Fault;", "    RETURN;"]
    b += [f"IF NOT ({fin}) THEN", "    s_Fault := s_Fault OR 16#1;", *ret, "END_IF;",
          "IF NOT (P_TORQUE_MIN <= P_TORQUE_MAX) THEN", "    s_Fault := s_Fault OR 16#4;", *ret, "END_IF;",
          "t_Wf := P_A_W * s_WFilt + P_ONE_MINUS_A_W * (DINT_TO_%s(t_Dn) * P_RAD_PER_COUNT) / P_TS;" % R,
          _st_flush("t_Wf"), "t_W := t_Wf;"]
    for i in range(ns):
        b += [f"t_Y := P_SF{i}_B0 * t_W + P_SF{i}_B1 * s_SF{i}_X1 + P_SF{i}_B2 * s_SF{i}_X2 - P_SF{i}_A1 * s_SF{i}_Y1 "
              f"- P_SF{i}_A2 * s_SF{i}_Y2;", _st_flush("t_Y"), f"t_SF{i} := t_Y;", "t_W := t_Y;"]
    b += ["IF P_KD <> 0.0 THEN", "    t_Dv := P_BETA * s_Deriv + P_ONE_MINUS_BETA * (t_W - s_WPrev) / P_TS;",
          "    " + _st_flush("t_Dv"), "ELSE", "    t_Dv := 0.0;", "END_IF;"]
    if p is None:
        b += ["t_Ref := SpeedRef;", "t_TauFF := P_TAU_FF;"]
    else:
        b += [f"t_PendW{i} := s_PendW{i}; t_PendT{i} := s_PendT{i};" for i in range(1, p.delay + 1)]
        b += ["t_PIntegral := s_PIntegral;", "t_WRef := s_WRef;", "t_TauP := s_TauP;", "t_Phase := s_Phase;",
              "IF t_Phase = 0 THEN (* position-loop sample *)",
              "    IF s_Travel < 16#80000000 THEN t_Trav := UDINT_TO_DINT(s_Travel); "
              "ELSE t_Trav := -UDINT_TO_DINT(16#FFFFFFFF - s_Travel) - 1; END_IF;",
              f"    t_Ep := (PosRef / P_UNIT_M - DINT_TO_{R}(t_Trav) * P_POS_PER_COUNT) * P_ERR_TO_RAD;",
              "    IF NOT Hold THEN t_PIntegral := t_PIntegral + P_TP_KIP * t_Ep; END_IF;",
              "    t_WRef := P_KV * t_Ep + t_PIntegral + P_KVFF * VelRef / P_LEAD;"]
        if fric:
            b += ["    t_FrW := VelRef / P_LEAD;", "    t_FrX := t_FrW / P_FR_WS;",
                  "    IF t_FrW > 0.0 THEN",
                  "        t_TauFr := P_FR_G * (P_FR_CP + P_FR_SP * EXP(-(t_FrX * t_FrX)) + P_FR_VP * t_FrW);",
                  "    ELSIF t_FrW < 0.0 THEN",
                  "        t_TauFr := P_FR_G * -(P_FR_CN + P_FR_SN * EXP(-(t_FrX * t_FrX)) - P_FR_VN * t_FrW);",
                  "    ELSE", "        t_TauFr := 0.0;", "    END_IF;",
                  "    t_TauP := P_KAFF_J * AccRef / P_LEAD + t_TauFr;"]
        else:
            b.append("    t_TauP := P_KAFF_J * AccRef / P_LEAD;")
        if p.delay:
            b += [f"    (* computation delay of {p.delay} position sample(s): the oldest pending output is applied *)",
                  "    t_NewW := t_WRef; t_NewT := t_TauP;", f"    t_WRef := t_PendW{p.delay}; t_TauP := t_PendT{p.delay};"]
            b += [f"    t_PendW{i} := t_PendW{i - 1}; t_PendT{i} := t_PendT{i - 1};" for i in range(p.delay, 1, -1)]
            b += ["    t_PendW1 := t_NewW; t_PendT1 := t_NewT;"]
        b += ["END_IF;", "IF t_Phase + 1 >= P_POSITION_RATE THEN t_Phase := 0; ELSE t_Phase := t_Phase + 1; END_IF;",
              "t_Ref := t_WRef;", "t_TauFF := P_TAU_FF + t_TauP;"]
    b += ["t_E := t_Ref - t_W;", "t_U := P_KP * (P_B_SP * t_Ref - t_W) + s_Integral - P_KD * t_Dv + t_TauFF;",
          "IF t_U > P_TORQUE_MAX THEN t_Us := P_TORQUE_MAX; ELSIF t_U < P_TORQUE_MIN THEN t_Us := P_TORQUE_MIN; "
          "ELSE t_Us := t_U; END_IF;",
          "IF Hold THEN t_Int := s_Integral; ELSE t_Int := s_Integral + P_TS * (P_KI * t_E + P_K_AW * (t_Us - t_U)); "
          "END_IF;", "t_Uf := t_Us;"]
    for i in range(nt):
        b += [f"t_Y := P_TF{i}_B0 * t_Uf + P_TF{i}_B1 * s_TF{i}_X1 + P_TF{i}_B2 * s_TF{i}_X2 - P_TF{i}_A1 * s_TF{i}_Y1 "
              f"- P_TF{i}_A2 * s_TF{i}_Y2;", _st_flush("t_Y"), f"t_TF{i} := t_Y;", "t_Uf := t_Y;"]
    if nt:
        b.append("IF t_Uf > P_TORQUE_MAX THEN t_Uf := P_TORQUE_MAX; ELSIF t_Uf < P_TORQUE_MIN THEN "
                 "t_Uf := P_TORQUE_MIN; END_IF;")
    b += [f"IF NOT ({_st_fin('t_U')} AND {_st_fin('t_Uf')} AND {_st_fin('t_Int')}) THEN",
          "    s_Fault := s_Fault OR 16#2;", *ret, "END_IF;"]
    for line in state_moves(ns, nt, None if p is None else p.delay, law.delay_samples):
        if line is ENABLE_GATE:
            b += ["IF NOT Enable THEN", *ret, "END_IF;"]
        else:
            b.append(" ".join(f"{_st_name(dst)} := {_st_name(src)};" for dst, src in line))
    b += ["TorqueCmd := s_UOut;", "Fault := s_Fault;"]
    return {"name": n, "comment": _header_comment(law, "st"), "inputs": ins, "outputs": outs, "locals": loc, "body": b}


def st_code(law: "DriveLaw", *, name: str = "PrsaCtrl", real: str = "double", differences: str = "counts") -> str:
    """The law as an IEC 61131-3 Structured Text FUNCTION_BLOCK (compiles with matiec's
    ``iec2c``; internal names carry ``s_``/``t_`` prefixes, parameters ``P_``, so no name meets a
    keyword or a standard library block).

    Inputs: ``Reset`` (load the ``Init*`` values), ``Enable``, ``Hold``, ``EncCount`` (DINT, raw
    32-bit counts, wrap-safe), ``SpeedRef`` (rad/s; speed loop) or ``PosRef`` (m), ``VelRef``
    (m/s), ``AccRef`` (m/s^2) (cascade) and ``PosCount`` (DINT, linear-scale counts);
    ``CountModulus``; the run-time parameters ``P_*`` (write them at any time). Outputs
    ``TorqueCmd`` (N m), ``Speed``, ``CommandUnfiltered``, ``Fault`` (DWORD). Call once per
    sample time from a cyclic task of period ``Ts``; the behaviour equals :func:`c_code`.

    Parameters
    ----------
    law : DriveLaw
    name : str
        Name of the function block.
    real : {"double", "float"}
        ``LREAL`` or ``REAL``.
    differences : {"counts"}
    """
    _check_differences(differences)
    parts = st_parts(law, name=name, real=real)
    out = [f"FUNCTION_BLOCK {parts['name']}", *[_st_comment(s) for s in parts["comment"]]]

    def decl(kind: str, items: list) -> list[str]:
        lines = [kind]
        for nm, typ, init, com in items:
            lines.append(f"    {nm} : {typ}" + (f" := {init}" if init is not None else "") + ";"
                         + (f" {_st_comment(com)}" if com else ""))
        return lines + ["END_VAR"]

    out += decl("VAR_INPUT", parts["inputs"]) + decl("VAR_OUTPUT", parts["outputs"]) + decl("VAR", parts["locals"])
    out += ["", *parts["body"], "END_FUNCTION_BLOCK", ""]
    return "\n".join(out)
