"""Expensive runs shared by the tests that only read their results (tests/conftest.py's
``shared_tuning``, ``paper_report`` and ``default_cli_run``; tests/io/test_plcopen.py's move export)."""

from __future__ import annotations

#: The runs ``shared_tuning`` keeps: ``(result, warnings, progress lines)`` by the function and the
#: pickled value of its arguments; at most ``_TUNINGS_MAX`` (the oldest dropped).
_TUNINGS: dict = {}
_TUNINGS_MAX = 8


def tuned_once(real, *args, calls=None, progress=None, **kwargs):
    """``real(*args, **kwargs)`` once per function and value of its arguments (their pickled
    bytes) in the session. At every call the first run's warnings are emitted (through the
    caller's filters), and at a call after the first its progress lines are said again to
    ``progress`` (what the solvers print themselves is not printed again: for commands run
    without ``--verbose``); ``calls`` (a list) receives ``(key, hit)``."""
    import pickle
    import warnings

    calls = [] if calls is None else calls
    try:
        key = (real.__module__, real.__qualname__, pickle.dumps((args, sorted(kwargs.items()))))
    except Exception:  # noqa: BLE001 - an argument that does not pickle is tuned, not shared
        calls.append((None, False))
        return real(*args, **kwargs, **({"progress": progress} if progress is not None else {}))
    hit = key in _TUNINGS
    calls.append((key, hit))
    if not hit:
        said: list = []

        def say(line):
            said.append(line)
            progress(line)

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = real(*args, **kwargs, **({"progress": say} if progress is not None else {}))
        while len(_TUNINGS) >= _TUNINGS_MAX:
            _TUNINGS.pop(next(iter(_TUNINGS)))
        _TUNINGS[key] = result, list(caught), said
    result, caught, said = _TUNINGS[key]
    for line in said if hit and progress is not None else ():
        progress(line)
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return list(result) if isinstance(result, list) else result


def share_tunings(mp, calls=None):
    """Patch ``tune_actuator`` and ``tune_move`` (where the commands look them up) with their
    shared runs (:func:`tuned_once`)."""
    import prsa_ctrl.studies.autotune as autotune
    import prsa_ctrl.studies.move as move

    real_tune, real_move = autotune.tune_actuator, move.tune_move
    # ``resolved`` (a scene kind's resolve_scene(plant, scene)) is a function of the plant and the
    # scene alone: the shared run resolves them itself, so calls with and without it share one run
    mp.setattr(autotune, "tune_actuator", lambda plant, scene, workers=None, resolved=None: tuned_once(
        real_tune, plant, scene, workers=workers, calls=calls))
    mp.setattr(move, "tune_move", lambda plant, scene, progress=None: tuned_once(
        real_move, plant, scene, calls=calls, progress=progress))
