"""One plant description (issue 21, EMPS): the plant file prsa-fit writes for a linear axis is a
plant file of the toolkit (schema defaults and sources, load_plant, --show-plant, linearisation,
simulation), and reports say the coordinates."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from prsa_ctrl.cli.fit import main as fit_main
from prsa_ctrl.cli.tune import main as tune_main
from prsa_ctrl.identification.axis import DEFAULTS, PARAMETERS, load_axis_plant
from prsa_ctrl.plant import describe_plant, linear_core, load_plant
from prsa_ctrl.plant.model import plant_model
from prsa_ctrl.plant.schema import DEFAULTS as SCHEMA_DEFAULTS

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "emps"
DATA = EXAMPLE / "DATA_EMPS.mat"
needs_data = pytest.mark.skipif(not DATA.is_file(), reason="examples/emps/DATA_EMPS.mat not in this checkout")


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("emps")
    out, js = d / "F.toml", d / "FIT.json"
    assert fit_main([str(DATA), "--log-format", str(EXAMPLE / "log.toml"), "--out", str(out), "--json", str(js)]) == 0
    return out, json.loads(js.read_text())


def test_the_axis_defaults_are_the_schemas():
    assert set(DEFAULTS) == set(PARAMETERS[1:])
    for k, v in DEFAULTS.items():
        assert v == SCHEMA_DEFAULTS[k]


@needs_data
def test_fitted_file_is_a_toolkit_plant_file(fitted, capsys):
    out, rep = fitted
    assert rep["coordinates"] == "load (position m, force N)" and rep["mechanism"] == "linear-axis"
    axis = load_axis_plant(out)
    plant = load_plant(out)
    assert plant.mechanism == "linear-axis"
    for k, v in axis.values.items():  # the same values and sources through both readers
        assert plant.values[k] == v and plant.sources[k] == axis.sources[k]
    assert plant.values["axis.mass_kg"] == pytest.approx(rep["equivalent"]["mass_kg"]["value"], rel=1e-12)
    assert plant.sources["friction.efficiency"].startswith("derived:")
    assert dict(axis.to_plant().values) == dict(plant.values)
    lines = describe_plant(plant).splitlines()
    assert lines[2] == "coordinates: load (position m, force N)"
    assert describe_plant(load_plant()).splitlines()[2] == "coordinates: motor (angle rad, torque N m)"
    capsys.readouterr()
    assert tune_main(["--show-plant", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "coordinates: load (position m, force N)" in shown and "fit: DATA_EMPS.mat" in shown


@needs_data
def test_fitted_plant_linearises_and_simulates(fitted):
    out, _ = fitted
    plant = load_plant(out)
    v = plant.values
    names = plant_model(plant, "rigid").state_names
    i_v = names.index("omega_nut")
    for speed, fv in ((1e-3, v["friction.viscous_positive_n_s_per_m"]), (-1e-3, v["friction.viscous_negative_n_s_per_m"])):
        a, b, *_ = linear_core(plant, speed, 0.0, "rigid")
        assert a[i_v, i_v] == pytest.approx(-fv / v["axis.mass_kg"], rel=1e-9)  # m/s per m/s: load coordinates
        assert b[i_v, 1] == pytest.approx(-1.0 / v["axis.mass_kg"], rel=1e-9)  # an axial load of 1 N, against +x
    from prsa_ctrl.drive.pid import PID
    from prsa_ctrl.sim.engine import run

    r = run(plant, setpoint=0.05, load=0.0, duration=0.3, controller=PID(4000.0, 40000.0), fidelity="rigid",
            discrete=True)
    speed = r.states[r.state_labels.index("omega_nut")]
    assert np.all(np.isfinite(speed)) and abs(speed[-1] - 0.05) < 0.005  # m/s


@needs_data
def test_validate_json_names_the_coordinates(fitted, tmp_path, capsys):
    out, _ = fitted
    rj = tmp_path / "R.json"
    capsys.readouterr()
    assert fit_main(["--validate", str(out), str(DATA), "--log-format", str(EXAMPLE / "log.toml"), "--json", str(rj)]) == 0
    assert "coordinates: load (position m, force N)" in capsys.readouterr().out
    rep = json.loads(rj.read_text())
    assert rep["coordinates"] == "load (position m, force N)" and rep["mechanism"] == "linear-axis"


def test_a_fit_without_a_controller_writes_a_loadable_plant(tmp_path, capsys):
    """No --plant and no controller: the force limit is estimated from the log (and says so), so the
    written file has every required key."""
    n, h, m, f0 = 3000, 1e-3, 4.0, 2.0
    t = np.arange(n) * h
    f = f0 * np.sign(np.sin(2 * math.pi * 2.0 * t))
    v = np.zeros(n)
    x = np.zeros(n)
    for k in range(n - 1):  # a free mass, exact over each held sample
        v[k + 1] = v[k] + f[k] / m * h
        x[k + 1] = x[k] + v[k] * h + 0.5 * f[k] / m * h * h
    path = tmp_path / "log.csv"
    path.write_text("time_s,position_m,speed_m_s,force_n\n"
                    + "".join(f"{a:.17g},{b:.17g},{c:.17g},{d:.17g}\n" for a, b, c, d in zip(t, x, v, f)))
    fmt = tmp_path / "fmt.toml"
    fmt.write_text('format = "csv"\n[time]\nname = "time_s"\nunit = "s"\n[position]\nname = "position_m"\nunit = "m"\n'
                   '[speed]\nname = "speed_m_s"\nunit = "m/s"\n[command]\nname = "force_n"\nunit = "N"\n')
    out = tmp_path / "F.toml"
    code = fit_main([str(path), "--log-format", str(fmt), "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    plant = load_plant(out)
    assert plant.values["drive.force_limit_n"] == pytest.approx(f0, rel=1e-12)
    assert plant.sources["drive.force_limit_n"].startswith("estimate: largest force in log.csv")
    assert plant.values["axis.mass_kg"] == pytest.approx(m, rel=1e-3)


def test_a_tiny_viscous_term_replays_as_none():
    """The stop time of a decelerating axis with a viscous term ``k = Fv/M`` is ``-log1p(k v/a)/k``:
    with ``log(1 + k v/a)`` a tiny ``Fv`` (as a fit at its bound 0 probes it) lost every digit and
    the replay jumped by percent."""
    from prsa_ctrl.identification.axis import simulate_axis
    from prsa_ctrl.identification.logformat import AxisLog

    n, h = 1500, 1e-3
    t = np.arange(n) * h
    f = 2.0 * np.sign(np.sin(2 * math.pi * 2.0 * t))  # accelerate, brake to rest, again
    log = AxisLog("brake", t, np.zeros(n), f, "N", 1.0, h)
    ref = simulate_axis((4.0, 0.0, 0.0, 1e-3, 0.0), log, x0=(0.0, 0.0)).position_m
    for fv in (1e-13, 1e-9):
        x = simulate_axis((4.0, fv, 0.0, 1e-3, 0.0), log, x0=(0.0, 0.0)).position_m
        assert np.max(np.abs(x - ref)) < 1e-9 * np.max(np.abs(ref)) + 1e-3 * fv
