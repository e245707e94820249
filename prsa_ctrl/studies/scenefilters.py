"""A scene's loop filters: the ``[filters]`` table of a scene file and ``prsa-tune --filter``.

Notch and low-pass filters in the drive's speed-measurement and torque-command paths, in the
units of :mod:`prsa_ctrl.drive.filters` (Hz, dB)::

    [[filters.notch]]
    path = "torque"        # "torque": on the torque command; "speed": on the measured speed
    centre_hz = 163.0      # centre frequency, Hz
    width_hz = 40.0        # -3 dB width of the full notch, Hz (quality centre_hz / width_hz)
    depth_db = -20.0       # gain at the centre, dB, <= 0 (default -20)

    [[filters.lowpass]]
    path = "speed"
    corner_hz = 400.0      # corner (order 1: -3 dB) or natural (order 2) frequency, Hz
    order = 2              # 1 or 2 (default 1)
    damping = 0.7071       # order 2 only (default 1/sqrt(2), Butterworth)

On the command line the same keys: ``--filter notch:path=torque,centre_hz=163,width_hz=40,depth_db=-20``
(repeatable; the filters given replace the scene's). Each filter runs as the Tustin biquad
prewarped at its centre/corner at the plant's sample time (:class:`prsa_ctrl.drive.filters.LoopFilter`),
in the loop models, the simulator and the export alike; several filters on one path run in the
order written (the scene file's notches before its low-passes).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from ..options import check_number
from ..textsafe import quote
from ..drive.filters import NYQUIST_MARGIN, FirstOrderLowPass, LoopFilter, Notch, SecondOrderLowPass, loop_filters
from ..errors import SceneError

__all__ = ["FILTER_PATHS", "FILTER_KEYS", "MAX_SCENE_FILTERS", "parse_filters", "filter_entry", "parse_filter_flag",
           "check_filters_against_plant", "filter_rows", "scene_filters", "describe_filters"]

#: ``path`` values and the place in the drive's loop each means (:data:`prsa_ctrl.drive.filters.PLACES`).
FILTER_PATHS = {"speed": "speed_measurement", "torque": "torque_command"}
#: Keys of each kind of filter entry (``path`` is required, so are the frequencies and the notch width).
FILTER_KEYS = {"notch": ("path", "centre_hz", "width_hz", "depth_db"),
               "lowpass": ("path", "corner_hz", "order", "damping")}
#: At most this many filters in one loop (:func:`prsa_ctrl.drive.filters.loop_filters`).
MAX_SCENE_FILTERS = 8
_REQUIRED = {"notch": ("path", "centre_hz", "width_hz"), "lowpass": ("path", "corner_hz")}


def filter_entry(kind: str, values: Mapping[str, Any], where: str, sep: str = ".",
                 typed: Mapping[str, str] | None = None) -> LoopFilter:
    """One filter entry as a :class:`~prsa_ctrl.drive.filters.LoopFilter`.

    Parameters
    ----------
    kind : {"notch", "lowpass"}
    values : mapping
        The entry's keys (:data:`FILTER_KEYS`) and values (Hz, dB; ``path`` a string).
    where : str
        How messages name the entry (``"scene.toml: filters.notch[1]"``, ``"--filter 'notch:...'"``).
    sep : str
        Between ``where`` and a key in messages (``"."`` in a file, ``": "`` on the command line).
    typed : mapping, optional
        Key -> the value as the user typed it (messages quote it; default its ``repr``).

    Raises
    ------
    SceneError
        One line naming the entry, the key and the value as given, and what was expected.
    """
    if kind not in FILTER_KEYS:
        raise SceneError(f"{where}: filter kind {quote(kind)}; expected notch or lowpass")
    if not isinstance(values, Mapping):
        raise SceneError(f"{where} = {quote(values)}; expected a table of {', '.join(FILTER_KEYS[kind])}")
    typed = dict(typed or {})

    def shown(key: str) -> str:
        return typed.get(key, repr(values[key]))

    for key in values:
        if key not in FILTER_KEYS[kind]:
            raise SceneError(f"{where}{sep}{key} = {shown(key)}: unknown key; expected one of "
                             f"{', '.join(FILTER_KEYS[kind])}")
    for key in _REQUIRED[kind]:
        if key not in values:
            raise SceneError(f"{where}: {key} missing; expected {', '.join(_REQUIRED[kind])} "
                             f"(and optionally {', '.join(k for k in FILTER_KEYS[kind] if k not in _REQUIRED[kind])})")
    path = values["path"]
    if path not in FILTER_PATHS:
        raise SceneError(f"{where}{sep}path = {shown('path')}; expected \"speed\" (the measured speed) or \"torque\" "
                         "(the torque command)")
    nums = {k: check_number(f"{where}{sep}{k}", v, typed=shown(k), error=SceneError)
            for k, v in values.items() if k != "path"}
    freq = "centre_hz" if kind == "notch" else "corner_hz"
    if not nums[freq] > 0:
        raise SceneError(f"{where}{sep}{freq} = {shown(freq)}; expected a frequency > 0 Hz")
    if kind == "notch":
        if not nums["width_hz"] > 0:
            raise SceneError(f"{where}{sep}width_hz = {shown('width_hz')}; expected a width > 0 Hz")
        if nums.get("depth_db", -20.0) > 0:
            raise SceneError(f"{where}{sep}depth_db = {shown('depth_db')}; expected a depth <= 0 dB (a notch "
                             "attenuates: -20 dB is a gain of 0.1 at the centre)")
        make = lambda: Notch(nums["centre_hz"], nums["width_hz"], nums.get("depth_db", -20.0))  # noqa: E731
    else:
        order = values.get("order", 1)
        if isinstance(order, bool) or order not in (1, 2):
            raise SceneError(f"{where}{sep}order = {shown('order')}; expected 1 or 2")
        if order == 1 and "damping" in values:
            raise SceneError(f"{where}{sep}damping = {shown('damping')}; expected no damping with order = 1 "
                             "(a first-order low-pass has none)")
        if order == 1:
            make = lambda: FirstOrderLowPass(nums["corner_hz"])  # noqa: E731
        else:
            make = lambda: SecondOrderLowPass(nums["corner_hz"], nums.get("damping", 1.0 / math.sqrt(2.0)))  # noqa: E731
    try:
        filt = make()
    except ValueError as exc:  # the filter's own range check, e.g. width_hz = ...; expected ...
        raise SceneError(f"{where}{sep}{exc}") from None
    return LoopFilter(filt, FILTER_PATHS[path])


def scene_filters(scene: Any) -> tuple[tuple[LoopFilter, ...], tuple[str, ...]]:
    """A scene's filters normalised (:func:`prsa_ctrl.drive.filters.loop_filters`: ``LoopFilter``
    items or ``(place, Filter)`` pairs) with a label each, refused where the loop has none.

    Raises
    ------
    SceneError
        Filters that are not filters, or filters on a continuous loop.
    """
    try:
        filters = loop_filters(scene.filters)
    except ValueError as exc:
        raise SceneError(f"{scene.origin}: filters: {exc}") from None
    labels = tuple(scene.filter_labels)
    if len(labels) != len(filters):
        labels = tuple(f"{scene.origin}: filters[{i}] at {quote(lf.filter.characteristic_hz)} Hz"
                       for i, lf in enumerate(filters, start=1))
    if filters and not scene.discrete:
        raise SceneError(f"{scene.origin}: discrete = false with filters; expected discrete = true (the filters "
                         "run as biquads at the drive's sample time)")
    return filters, labels


def parse_filters(table: Any, origin: str) -> tuple[tuple[LoopFilter, ...], tuple[str, ...]]:
    """The ``[filters]`` table of a scene file: the filters and how messages name each entry.

    Parameters
    ----------
    table : mapping
        ``{"notch": [entries], "lowpass": [entries]}`` (TOML arrays of tables; 1-based in messages).
    origin : str
        The scene file, as messages name it.

    Returns
    -------
    (tuple of LoopFilter, tuple of str)
        Notches first, then low-passes, each in file order; labels naming each entry's
        frequency as written (``"<origin>: filters.notch[1].centre_hz = 163.0"``).
    """
    if not isinstance(table, Mapping):
        raise SceneError(f"{origin}: filters = {quote(table)}; expected a table with [[filters.notch]] and/or "
                         "[[filters.lowpass]] entries")
    for kind, entries in table.items():
        if kind not in FILTER_KEYS:
            raise SceneError(f"{origin}: filters.{kind} = {quote(entries)}: unknown filter kind; expected "
                             "[[filters.notch]] or [[filters.lowpass]]")
        if not isinstance(entries, list):
            raise SceneError(f"{origin}: filters.{kind} = {quote(entries)}; expected an array of tables "
                             f"([[filters.{kind}]] entries)")
    filters, labels = [], []
    for kind in FILTER_KEYS:
        for i, entry in enumerate(table.get(kind, []), start=1):
            where = f"{origin}: filters.{kind}[{i}]"
            filters.append(filter_entry(kind, entry, where))
            freq = "centre_hz" if kind == "notch" else "corner_hz"
            labels.append(f"{where}.{freq} = {quote(entry[freq])}")
    if len(filters) > MAX_SCENE_FILTERS:
        raise SceneError(f"{origin}: [filters] has {len(filters)} entries; expected at most {MAX_SCENE_FILTERS}")
    return tuple(filters), tuple(labels)


def parse_filter_flag(text: str) -> tuple[LoopFilter, str, str]:
    """``--filter KIND:key=value,...`` (the scene file's keys), e.g.
    ``notch:path=torque,centre_hz=163,width_hz=40,depth_db=-20`` or ``lowpass:path=speed,corner_hz=400,order=2``.

    Returns
    -------
    (LoopFilter, str, str)
        The filter, the flag as typed (``--filter notch:...``) and the label naming its frequency
        as typed (for the checks against the plant).

    Raises
    ------
    SceneError
        One line quoting the flag.
    """
    where = f"--filter {quote(text)}"
    kind, sep, rest = text.partition(":")
    kind = kind.strip()
    if not sep or kind not in FILTER_KEYS:
        raise SceneError(f"{where}: expected notch:path=torque|speed,centre_hz=F,width_hz=W[,depth_db=D] or "
                         "lowpass:path=torque|speed,corner_hz=F[,order=1|2][,damping=Z]")
    values: dict[str, Any] = {}
    typed: dict[str, str] = {}
    for item in rest.split(","):
        key, eq, val = item.partition("=")
        key, val = key.strip(), val.strip()
        if not eq or not key or not val:
            raise SceneError(f"{where}: {quote(item.strip())} is not key=value; expected e.g. centre_hz=163")
        if key in values:
            raise SceneError(f"{where}: {key} given twice; expected each key once")
        typed[key] = val
        if key == "path":
            values[key] = val
        elif key == "order" and val in ("1", "2"):
            values[key] = int(val)
        else:
            try:
                values[key] = float(val)
            except ValueError:
                values[key] = val  # named in the entry's own message (unknown key or not a number)
    freq = "centre_hz" if kind == "notch" else "corner_hz"
    return filter_entry(kind, values, where, ": ", typed), f"--filter {text}", f"{where}: {freq} = {typed.get(freq)}"


def check_filters_against_plant(filters, labels, sample_time_s: float, plant_name: str) -> None:
    """Refuse a filter the drive cannot run at its sample time: a centre/corner at or above the
    Nyquist frequency ``1/(2 ts)`` or within :data:`~prsa_ctrl.drive.filters.NYQUIST_MARGIN` (1 %)
    of it (or too low to discretise). Called before any tuning.

    Raises
    ------
    SceneError
        One line naming the entry, the frequency as typed, the plant's Nyquist frequency and the
        margin.
    """
    nyquist = 0.5 / sample_time_s
    for lf, where in zip(filters, labels):
        if not lf.filter.characteristic_hz <= nyquist * (1.0 - NYQUIST_MARGIN):
            raise SceneError(f"{where}; expected a frequency below the Nyquist frequency {nyquist:g} Hz of "
                             f"{plant_name} (sensor.sample_time_s = {sample_time_s:g} s) by at least "
                             f"{NYQUIST_MARGIN:.0%} of it (at most {nyquist * (1.0 - NYQUIST_MARGIN):g} Hz)")
        try:
            lf.biquad(sample_time_s)
        except ValueError as exc:
            raise SceneError(f"{where}: {exc}") from None


def describe_filters(filters, sample_time_s: float) -> list[str]:
    """One line per filter in drive terms: path, frequency, width/depth or order, and the biquad
    the drive runs at the sample time (for the text report)."""
    lines = []
    for row in filter_rows(filters, sample_time_s):
        q = row["biquad"]
        where = "speed measurement" if row["path"] == "speed" else "torque command"
        if row["kind"] == "notch":
            what = (f"notch on the {where}: centre {row['centre_hz']:.5g} Hz, width {row['width_hz']:.5g} Hz "
                    f"(Q {row['quality']:.3g}), depth {row['depth_db']:.4g} dB")
        elif row["kind"] == "lowpass1":
            what = f"first-order low-pass on the {where}: corner {row['corner_hz']:.5g} Hz"
        else:
            what = (f"second-order low-pass on the {where}: corner {row['corner_hz']:.5g} Hz, "
                    f"damping {row['damping']:.4g}")
        lines.append(f"{what}; biquad at {sample_time_s * 1e3:.4g} ms (Tustin, prewarped): b = [{q['b0']:.10g}, "
                     f"{q['b1']:.10g}, {q['b2']:.10g}], a = [1, {q['a1']:.10g}, {q['a2']:.10g}]")
    return lines


def filter_rows(filters, sample_time_s: float) -> list[dict]:
    """The filters in drive terms (JSON): path, kind, parameters (Hz, dB) and the biquad the
    drive runs at the sample time (Tustin prewarped, ``a0 = 1``)."""
    rows = []
    for lf in filters:
        d = lf.as_dict(sample_time_s)
        path = next(k for k, v in FILTER_PATHS.items() if v == lf.place)
        rows.append({"path": path, **d})
    return rows
