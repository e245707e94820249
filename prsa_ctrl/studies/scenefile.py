"""Scene files: where they are, how they are read, and the limits every scene kind is checked
against (speed-loop scenes in :mod:`prsa_ctrl.studies.scene`, move scenes in
:mod:`prsa_ctrl.studies.move`).

A scene is named by a built-in name (``paper-load-step``: ``tuning/paper-load-step.toml`` of the
package) or a path (anything ending in ``.toml`` or containing ``/``). Which kind of scene a file
is, the scene types say (:func:`prsa_ctrl.studies.scene.parse_scene`, ``SCENE_TYPES``).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from ..textsafe import quote
from ..options import SPEED_MAX_RPM
from ..errors import SceneError
from ..tomlfile import read_toml
from ..plant.plantfile import builtin_root

__all__ = ["parse_load_step", "DEFAULT_SCENE", "SETPOINT_MAX_RPM", "STICTION_MARGIN", "PRE_EVENT_SAMPLES", "POST_EVENT_SAMPLES",
           "MAX_RECORD_SAMPLES", "MAX_LOAD_LEVELS", "MIN_LOAD_STEP_N", "LOAD_CHANGE_TIME_RANGE_S",
           "builtin_scenes", "scene_root", "locate_scene", "read_scene_doc"]

DEFAULT_SCENE = "paper-load-step"

#: Highest nut-speed setpoint accepted, rpm (:data:`prsa_ctrl.options.SPEED_MAX_RPM`).
SETPOINT_MAX_RPM = SPEED_MAX_RPM
#: Lowest setpoint as a multiple of the speed at which the screw moves at the Stribeck velocity:
#: at 1x (3 rpm on paper-iprsm) the verified run of the paper plant goes non-finite, at 3x
#: (10 rpm) it is fine; 5x keeps a margin.
STICTION_MARGIN = 5.0
#: Controller samples of steady running needed before an event (load step): the verification
#: starts this many samples before it (``autotune._PRE_SAMPLES``) so that the sampled
#: controller, the speed filter and the ZOH are in their steady state when the load moves.
PRE_EVENT_SAMPLES = 8
#: Controller samples needed after the event: the fastest closed loop a sampled drive reaches
#: has a time constant of ~10 samples (crossover <= ~0.1 / Ts); the peak and the recovery need
#: at least 8 such time constants in the record.
POST_EVENT_SAMPLES = 80
#: Largest record, in controller samples over the whole duration: the tuner's prediction and
#: the verification record hold one point per sample and per load level (40 000 samples =
#: 10 s at 4 kHz, ~8 s of run time per verified second today).
MAX_RECORD_SAMPLES = 40_000
#: Most load levels per scene (each costs a linearisation, a tuner horizon and verified runs).
MAX_LOAD_LEVELS = 20
#: Smallest load step, N: smaller steps drown in the encoder quantisation and the metrics
#: become relative differences of numbers at numerical zero.
MIN_LOAD_STEP_N = 1.0
#: Range of ``[estimator] load_change_time_s``, s: the Kalman filter's load random walk has the
#: variance ``T_rated^2 Ts / t`` per sample; 1 ms is 4 samples of a 4 kHz drive (a faster
#: "change" is noise, not load), and beyond 1000 s the variance is ~1e-10 of the rated torque
#: squared per sample (1e300 underflows the Riccati equation).
LOAD_CHANGE_TIME_RANGE_S = (1e-3, 1e3)


def scene_root() -> Any:
    """The folder of the built-in scene files (package data, or ``tuning/`` of a checkout)."""
    return builtin_root("prsa_ctrl.scenes", "tuning")


def builtin_scenes() -> list[str]:
    """Names of the scene files shipped with the package (``tuning/*.toml``), both kinds."""
    return sorted(p.name[:-5] for p in scene_root().iterdir() if p.name.endswith(".toml"))


def _is_path(name_or_path: str | Path) -> bool:
    text = str(name_or_path)
    return isinstance(name_or_path, Path) or text.endswith(".toml") or "/" in text


def locate_scene(name_or_path: str | Path | None = None) -> tuple[Any, str, Any]:
    """The file of a scene: ``(file, origin, base)`` with ``origin`` the name the messages use
    (the path, or ``NAME.toml (built-in)``) and ``base`` the folder relative CSV traces are
    read from.

    Raises
    ------
    SceneError
        A path that is not a file, or an unknown built-in name (one line, the text as typed).
    """
    text = str(name_or_path if name_or_path is not None else DEFAULT_SCENE)
    if _is_path(name_or_path if name_or_path is not None else text):
        path = Path(text).expanduser()
        if not path.is_file():
            raise SceneError(f"scene file {quote(text)} not found; expected a readable .toml file")
        return path, str(path), path.parent
    root = scene_root()
    reader = root / f"{text}.toml"
    if not reader.is_file():
        raise SceneError(f"unknown scene {quote(text)}; expected a built-in name ({', '.join(builtin_scenes())}) or a .toml path")
    return reader, f"{text}.toml (built-in)", root


def read_scene_doc(reader: Any, origin: str) -> dict:
    """The TOML document of a scene file (a UTF-8 byte-order mark is dropped).

    Raises
    ------
    SceneError
        Unreadable file or invalid TOML, naming ``origin``.
    """
    try:
        text = reader.read_text(encoding="utf-8-sig")  # -sig: a byte-order mark is dropped
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{origin}: cannot be read ({exc.__class__.__name__}); expected a UTF-8 TOML file") from None
    return read_toml(text, origin, SceneError)


def parse_load_step(text: str) -> tuple[float, tuple[float, ...]]:
    """Parse ``INITIAL:FINAL[,FINAL...]`` (N), e.g. ``500:1500`` or ``500:1000,1500,2000`` (``prsa-tune
    --load-step``, the app's load-step field).

    Raises
    ------
    argparse.ArgumentTypeError
        One line quoting ``text``: malformed, non-finite or negative loads, a final load equal
        to the initial one, more than ``MAX_LOAD_LEVELS`` levels. Whether the plant can hold
        the loads is checked against the plant (:func:`prsa_ctrl.studies.scene.check_against_plant`).

    Examples
    --------
    >>> parse_load_step("500:1000,1500")
    (500.0, (1000.0, 1500.0))
    """
    expected = "expected INITIAL:FINAL[,FINAL...] in newtons >= 0, e.g. 500:1500"
    parts = text.split(":")
    if len(parts) != 2 or not parts[0].strip() or not parts[1].strip():
        raise argparse.ArgumentTypeError(f"{quote(text)}: {expected}")
    tokens = parts[1].split(",")
    if len(tokens) > MAX_LOAD_LEVELS:
        raise argparse.ArgumentTypeError(f"{text[:40]!r}...: {len(tokens)} load levels; expected at most {MAX_LOAD_LEVELS}")
    try:
        initial = float(parts[0])
        finals = tuple(float(p) for p in tokens)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{quote(text)}: {expected}") from None
    for tok, v in zip((parts[0], *tokens), (initial, *finals)):
        if not math.isfinite(v) or v < 0:
            raise argparse.ArgumentTypeError(f"{quote(text)}: load {tok.strip()} N is not allowed; {expected}")
    for f in finals:
        if f == initial:
            raise argparse.ArgumentTypeError(f"{quote(text)}: final load equals the initial load; expected a step")
    return initial, finals
