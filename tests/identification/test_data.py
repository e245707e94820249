"""prsa_ctrl.identification.data: loading and validating measured data for prsa-fit; experiment design."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prsa_ctrl.identification.data import (
    DataError,
    design_excitation,
    load_record,
    parse_columns,
    record_from_arrays,
)

TS = 2.5e-4


def _arrays(n=200, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * TS
    torque = 0.1 + 0.05 * np.sin(2 * np.pi * 20 * t) + 0.01 * rng.standard_normal(n)
    angle = 30.0 * t + 0.1 * np.sin(2 * np.pi * 10 * t)
    load = np.where(t > t[n // 2], 1500.0, 500.0)
    return {"time_s": t, "torque_command_n_m": torque, "nut_angle_rad": angle, "axial_load_n": load}


def _write(path, cols, header=None):
    header = header or list(cols)
    data = np.column_stack(list(cols.values()))
    lines = [",".join(header)] + [",".join(repr(float(v)) for v in row) for row in data]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_standard_file_round_trip(tmp_path):
    cols = _arrays()
    rec = load_record(_write(tmp_path / "d.csv", cols))
    assert rec.n == 200
    assert rec.sample_time_s == pytest.approx(TS)
    np.testing.assert_allclose(rec.nut_angle_rad, cols["nut_angle_rad"])
    np.testing.assert_allclose(rec.speed_rad_s, np.diff(cols["nut_angle_rad"]) / TS)
    assert rec.warnings == ()


def test_mapping_current_and_constant_load(tmp_path):
    cols = _arrays()
    renamed = {"t": cols["time_s"], "iq": cols["torque_command_n_m"] / 0.5, "enc": cols["nut_angle_rad"]}
    path = _write(tmp_path / "d.csv", renamed)
    rec = load_record(path, columns=parse_columns("time_s=t,current_a=iq,nut_angle_rad=enc"),
                      torque_constant_n_m_per_a=0.5, load_n=800.0)
    np.testing.assert_allclose(rec.torque_command_n_m, cols["torque_command_n_m"])
    assert np.all(rec.axial_load_n == 800.0)
    with pytest.raises(DataError, match="torque constant"):
        load_record(path, columns=parse_columns("time_s=t,current_a=iq,nut_angle_rad=enc"), load_n=800.0)


@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda c: c["time_s"].__setitem__(57, c["time_s"][56]), r"'time_s' line 59: .* duplicated"),
        (lambda c: c["time_s"].__setitem__(57, c["time_s"][55]), r"'time_s' line 59: .* backwards"),
        (lambda c: c["time_s"].__setitem__(slice(100, None), c["time_s"][100:] + 0.3 * TS), r"'time_s' line 102: interval"),
        (lambda c: c["torque_command_n_m"].__setitem__(10, np.nan), r"line 12: torque_command_n_m = 'nan'; expected a finite number"),
        (lambda c: c["nut_angle_rad"].__setitem__(3, np.inf), r"line 5: nut_angle_rad = 'inf'; expected a finite number"),
        (lambda c: c["torque_command_n_m"].__setitem__(slice(None), 0.2), r"'torque_command_n_m' lines 2\.\.201: constant"),
    ],
)
def test_bad_data_names_file_column_and_row(tmp_path, mutate, pattern):
    cols = {k: v.copy() for k, v in _arrays().items()}
    mutate(cols)
    path = _write(tmp_path / "bad.csv", cols)
    with pytest.raises(DataError, match=pattern) as exc:
        load_record(path)
    assert str(path) in str(exc.value)
    assert "\n" not in str(exc.value)


def test_structural_errors(tmp_path):
    cols = _arrays()
    p = _write(tmp_path / "u.csv", {**cols, "extra": cols["time_s"]})
    with pytest.raises(DataError, match="unknown column 'extra'"):
        load_record(p)
    p = _write(tmp_path / "m.csv", {k: v for k, v in cols.items() if k != "nut_angle_rad"})
    with pytest.raises(DataError, match="nut_angle_rad' or 'nut_speed_rad_s'"):
        load_record(p)
    p = _write(tmp_path / "l.csv", {k: v for k, v in cols.items() if k != "axial_load_n"})
    with pytest.raises(DataError, match="--load"):
        load_record(p)
    p = _write(tmp_path / "few.csv", {k: v[:10] for k, v in cols.items()})
    with pytest.raises(DataError, match="10 samples; expected at least"):
        load_record(p)
    p = tmp_path / "text.csv"
    p.write_text("time_s,torque_command_n_m,nut_angle_rad,axial_load_n\n0,abc,0,1\n")
    with pytest.raises(DataError, match=r" line 2: torque_command_n_m = 'abc'; expected a finite number"):
        load_record(p)
    with pytest.raises(DataError, match="not found"):
        load_record(tmp_path / "missing.csv")
    with pytest.raises(DataError, match="unknown name"):
        parse_columns("speed=rpm")


def test_rpm_speed_column_is_refused(tmp_path):
    cols = _arrays()
    speed = np.gradient(cols["nut_angle_rad"], TS) * 60 / (2 * math.pi)
    p = _write(tmp_path / "rpm.csv", {**cols, "nut_speed_rad_s": speed})
    with pytest.raises(DataError, match="nut_speed_rad_s.*looks like rpm"):
        load_record(p)
    ok = _write(tmp_path / "rad.csv", {**cols, "nut_speed_rad_s": speed * 2 * math.pi / 60})
    assert load_record(ok).nut_speed_rad_s is not None


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(row=st.integers(0, 199), col=st.sampled_from(["time_s", "torque_command_n_m", "nut_angle_rad", "axial_load_n"]),
       bad=st.sampled_from([float("nan"), float("inf"), float("-inf")]))
def test_any_non_finite_cell_is_located(row, col, bad):
    cols = {k: v.copy() for k, v in _arrays().items()}
    cols[col][row] = bad
    with pytest.raises(DataError) as exc:
        record_from_arrays("arr", cols["time_s"], cols["torque_command_n_m"], nut_angle_rad=cols["nut_angle_rad"],
                           axial_load_n=cols["axial_load_n"])
    assert str(exc.value) == f"arr row {row}: {col} = {bad!r}; expected a finite number"


@settings(max_examples=30, deadline=None)
@given(n=st.integers(50, 400), ts=st.floats(1e-5, 1e-2), jitter=st.floats(0.0, 0.009))
def test_valid_sampling_is_accepted(n, ts, jitter):
    rng = np.random.default_rng(n)
    t = np.arange(n) * ts + jitter * ts * rng.uniform(-0.5, 0.5, n)
    rec = record_from_arrays("ok", t, np.sin(np.arange(n)), nut_angle_rad=np.cos(np.arange(n) / 7), axial_load_n=100.0)
    assert rec.n == n
    assert rec.sample_time_s == pytest.approx(ts, rel=0.02)


@pytest.mark.parametrize("kind", ["multisine", "chirp", "steps"])
def test_design_excitation(kind):
    t, v = design_excitation(kind, duration_s=1.0, sample_time_s=1e-3, f_min_hz=2, f_max_hz=100, amplitude=10, offset=20)
    assert len(t) == 1000
    assert np.all(np.isfinite(v))
    if kind == "steps":
        assert v.max() > 0 > v.min()  # through both directions
    else:
        assert abs(float(np.max(np.abs(v - 20))) - 10) < 1e-6 * 10 or float(np.max(np.abs(v - 20))) <= 10 + 1e-9
    with pytest.raises(ValueError, match="Nyquist"):
        design_excitation(kind, duration_s=1.0, sample_time_s=1e-3, f_max_hz=600)


def test_byte_order_mark_and_streamed_row_limit(tmp_path, monkeypatch):
    """Review findings 6 and 8: an Excel "CSV UTF-8" export (BOM) is read; a file over the row
    limit is refused when the limit is passed, naming the line."""
    import prsa_ctrl.identification.data as fd

    t = np.arange(300) * 2.5e-4
    rows = "".join(f"{a:.7f},{0.1 + 0.05 * math.sin(200 * a):.6f},{30 * a:.9f},800\n" for a in t)
    p = tmp_path / "bom.csv"
    p.write_bytes(b"\xef\xbb\xbf" + ("time_s,torque_command_n_m,nut_angle_rad,axial_load_n\n" + rows).encode())
    rec = fd.load_record(p)
    assert rec.n == 300
    monkeypatch.setattr(fd, "MAX_SAMPLES", 100)
    with pytest.raises(fd.DataError, match=r"bom\.csv: more than 100 data rows \(line 102\); expected at most 100"):
        fd.load_record(p)


def test_a_torque_constant_without_a_current_column_is_refused(tmp_path):
    """Was: accepted silently (the constant ignored)."""
    p = _write(tmp_path / "d.csv", _arrays())
    with pytest.raises(DataError, match=r"d\.csv: a torque constant of 0\.05 N m/A \(--torque-constant\) was given, "
                                        r"but the file has no current column 'current_a'"):
        load_record(p, torque_constant_n_m_per_a=0.05)
    cols = _arrays()
    cols["current_a"] = cols.pop("torque_command_n_m") / 0.05
    rec = load_record(_write(tmp_path / "i.csv", cols), torque_constant_n_m_per_a=0.05)
    np.testing.assert_allclose(rec.torque_command_n_m, cols["current_a"] * 0.05)


# --- scalar arguments: checked by options.check_number (one line, the value as given) -----------

@pytest.mark.parametrize("load, shown", [(True, "True"), ("500", "'500'"), (float("nan"), "nan"), ([1.0], "[1.0]")])
def test_a_bad_constant_load_is_one_line_naming_it(tmp_path, load, shown):
    cols = {k: v for k, v in _arrays().items() if k != "axial_load_n"}
    path = _write(tmp_path / "noload.csv", cols)
    with pytest.raises(DataError) as exc:  # a string was a TypeError from math.isfinite before
        load_record(path, load_n=load)
    assert str(exc.value) == f"load = {shown}; expected a finite axial load in N"


@pytest.mark.parametrize("kw, expected", [
    ({"speed_rad_s": float("inf")}, "demo: speed (rad/s) = inf; expected a finite number"),
    ({"load_n": "0"}, "demo: load (N) = '0'; expected a finite number"),
    ({"coherence_min": 1.0}, "demo: coherence threshold = 1.0; expected a finite number >= 0 and < 1"),
    ({"coherence_min": -0.1}, "demo: coherence threshold = -0.1; expected a finite number >= 0 and < 1"),
])
def test_bad_operating_point_of_a_frequency_response_is_named(kw, expected):
    from prsa_ctrl.identification.data import frf_from_arrays

    f = np.geomspace(1, 300, 20)
    with pytest.raises(DataError) as exc:
        frf_from_arrays("demo", f, 1 / (2.4e-4 * 2j * np.pi * f), **kw)
    assert str(exc.value) == expected


def test_a_non_finite_excitation_offset_is_refused():
    with pytest.raises(DataError, match=r"^offset = nan; expected a finite number$"):
        design_excitation("steps", offset=float("nan"))
