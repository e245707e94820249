"""prsa_ctrl.identification.calibrate: the report's text lines."""

from __future__ import annotations

from types import SimpleNamespace

from prsa_ctrl.identification.calibrate import result_lines, validation_lines

FORGED = "log.csv\n  verdict: the plant explains the data\n\x1b[31m"


def _validation(name: str, passes: bool) -> dict:
    e = {"fit_percent": 12.0, "error_rms_rad_s": 1.0, "noise_floor_rad_s": 0.1, "explained": False, "whiteness": None}
    return {"replay": "prediction-error replay", "written_plant": {name: e}, "rule": "the rule", "passes": passes,
            "reasons": [f"{name} is not explained"]}


def test_a_log_named_with_line_feeds_cannot_forge_a_report_line():
    """Was: the log's name went into the lines as typed, so ``prsa-fit`` (whose report keeps its
    line feeds) printed a file named ``log.csv<LF>  verdict: the plant explains the data`` as a
    verdict line of its own under a failed validation."""
    result = SimpleNamespace(
        parameters={"nut.inertia_kg_m2": {"value": 1e-4, "ci95": (0.9e-4, 1.1e-4), "unit": "kg m^2"}}, delay=None,
        solver={"validation": _validation(FORGED, passes=False)},
        reflected_inertia_kg_m2={"value": 1e-4, "ci95": (0.9e-4, 1.1e-4)}, fit_percent={FORGED: 12.0},
        warnings=(f"{FORGED}: a warning naming the log",))
    lines = result_lines(result, {FORGED: "motor (angle rad, torque N m)"})
    assert all("\n" not in x and "\x1b" not in x for x in lines), lines
    assert [x for x in lines if "verdict" in x and x.lstrip().startswith("verdict")] == [
        "  verdict: NOT validated: log.csv\\n  verdict: the plant explains the data\\n\\x1b[31m is not explained"]
    assert "fit 12.00 % on log.csv\\n  verdict: the plant explains the data\\n\\x1b[31m" in lines
    assert all("\n" not in x for x in validation_lines(_validation(FORGED, passes=True)))


def test_the_axial_mode_a_compliant_fit_started_from_is_written():
    """The compliant time-domain fit starts from the two-mass fit of a measured response
    (compliant.seed_from_frf) and fits and validates that plant; the file wrote only the fitted
    keys, so it kept the datasheet's mass, stiffness and damping, not the plant validated (foreign
    feed axis: 700 N/um and damping 0.03 written, 694.5 N/um and 0.0388 fitted and validated)."""
    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.calibrate import written_keys
    from prsa_ctrl.identification.compliant import SEED_KEYS

    base = load_plant("ballscrew-32x10")
    seeded = base.with_params({"axis.moving_mass_kg": 0.9 * base.values["axis.moving_mass_kg"],
                               "axis.nut_stiffness_n_per_um": 1.1 * base.values["axis.nut_stiffness_n_per_um"]},
                              name=base.name)
    fitted = seeded.with_params({"axis.motor_inertia_kg_m2": 1.05 * base.values["axis.motor_inertia_kg_m2"]}, name=base.name)
    keys, _ = written_keys(base, SimpleNamespace(plant_keys=("axis.motor_inertia_kg_m2",), plant=fitted))
    assert keys[0] == "axis.motor_inertia_kg_m2"
    assert {"axis.moving_mass_kg", "axis.nut_stiffness_n_per_um"} <= set(keys)
    assert "axis.axial_damping_ratio" not in keys  # not changed: the base's stays
    unseeded = base.with_params({"axis.motor_inertia_kg_m2": 1.05 * base.values["axis.motor_inertia_kg_m2"]}, name=base.name)
    keys, _ = written_keys(base, SimpleNamespace(plant_keys=("axis.motor_inertia_kg_m2",), plant=unseeded))
    assert not set(SEED_KEYS) & set(keys[1:])  # (the fitted key alone: no derived key either, nut.inertia_kg_m2)


def test_an_frf_current_loop_outside_the_users_bounds_is_written_with_the_fits_entry(tmp_path):
    """prsa-fit --frf: a drive whose current loop (300 Hz) lies outside the paper plant's
    absolute [uncertainty] bounds (700..1400 Hz): the fitted value is written with the fit's
    entry, one line names the key, its interval and the bounds as typed, and the text loads."""
    import tomllib
    import warnings

    import numpy as np

    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.calibrate import calibrate_frf
    from prsa_ctrl.identification.data import frf_from_arrays
    from prsa_ctrl.identification.frf import frf_response
    from prsa_ctrl.plant.plantfile import Plant
    from prsa_ctrl.plant.uncertainty import plant_uncertainty

    bw = "drive.current_loop_bandwidth_hz"
    base = load_plant()
    typed = base.uncertainty[bw]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        truth = base.with_params({bw: 300.0})
    f = np.geomspace(5, 1000, 60)
    rng = np.random.default_rng(3)
    g = frf_response(truth, f, speed_rad_s=30.0) * np.exp(0.01 * (rng.standard_normal(60) + 1j * rng.standard_normal(60)))
    frf_from_arrays("syn", f, g, coherence=np.full(60, 0.97)).to_csv(tmp_path / "bode.csv")
    cal = calibrate_frf([tmp_path / "bode.csv"], name="fitted")
    written = cal.result.plant.values[bw]
    assert not typed["low"] <= written <= typed["high"]  # the premise: the data contradict the user's range
    lines = [ln for ln in cal.lines if f"{bw} = " in ln and "outside the base plant's [uncertainty]" in ln]
    assert len(lines) == 1
    assert f"low = {typed['low']!r}, high = {typed['high']!r}" in lines[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        back = Plant.from_dict(tomllib.loads(cal.plant_text), origin="fitted.toml")
    (u,) = [u for u in plant_uncertainty(back).entries if u.key == bw]
    assert u.low <= back.values[bw] <= u.high
    assert back.uncertainty[bw]["source"].startswith("fit: ")


def test_a_compliant_fits_written_mode_is_the_written_files_at_the_stated_point():
    """The mode a compliant fit reports (``axial_mode_hz``, the 'axial mode of the written plant'
    line) is the written file's own compliant model linearised at the stated speed and load, and
    the point is in the report; a rigid fit quotes none (its stiffness is the datasheet's)."""
    import warnings

    from prsa_ctrl import load_plant
    from prsa_ctrl.identification.calibrate import fit_report, mode_line, written_mode
    from prsa_ctrl.identification.frf import axial_mode
    from prsa_ctrl.plant.plantfile import plant_file_path

    text = plant_file_path("ballscrew-32x10").read_text()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = load_plant("ballscrew-32x10")
    compliant = SimpleNamespace(solver={"fidelity": "compliant"})
    m = written_mode(compliant, text, 30.0, -800.0)
    assert m["value"] == axial_mode(plant, speed_rad_s=30.0, load_n=-800.0)["resonance_hz"]
    assert (m["speed_rad_s"], m["load_n"]) == (30.0, -800.0)
    # the nut loss on the whole force: the same file at +800 N has its mode elsewhere
    assert abs(written_mode(compliant, text, 30.0, 800.0)["value"] / m["value"] - 1) > 0.01
    assert "30 rad/s, -800 N" in mode_line(m)
    assert f"{m['value']:.5g} Hz" in mode_line(m)
    assert written_mode(SimpleNamespace(solver={"fidelity": "rigid"}), text, 30.0, 0.0) is None
    assert written_mode(compliant, None, 30.0, 0.0) is None  # no file written: no mode of it
    result = SimpleNamespace(as_dict=lambda: {"parameters": {}})
    assert fit_report(result, {}, mode=m)["axial_mode_hz"] == m
