"""prsa-fit --fit: an empty item or a repeated key is refused in one line naming the flag and the
item; an empty [uncertainty] correlation array is refused with a message whose braces are single."""

from __future__ import annotations

import pytest

from prsa_ctrl.cli.fit import main
from prsa_ctrl.errors import PlantFileError
from prsa_ctrl.plant.plantfile import Plant


@pytest.mark.parametrize("value, words", [
    ("axis.motor_inertia_kg_m2,,friction.efficiency", ["--fit", "empty item 2"]),
    ("axis.motor_inertia_kg_m2,friction.efficiency,friction.efficiency", ["--fit", "'friction.efficiency' given twice"]),
    (",", ["--fit", "empty item 1"]),
    ("", ["--fit", "at least one key"]),
])
def test_fit_list_refused(tmp_path, capsys, value, words):
    log = tmp_path / "x.csv"
    log.write_text("time_s,torque_command_n_m,nut_angle_rad\n0,0,0\n")
    out = tmp_path / "o.toml"
    code = main([str(log), "--fit", value, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and not out.exists(), err
    for w in words:
        assert w in err, err


def test_empty_correlation_message_braces():
    doc = {"name": "p", "mechanism": "linear-axis", "axis": {"mass_kg": {"value": 1.0, "source": "t"}},
           "drive": {"gain_n_per_unit": {"value": 1.0, "source": "t"}, "force_limit_n": {"value": 10.0, "source": "t"}},
           "sensor": {"sample_time_s": {"value": 1e-3, "source": "t"}, "encoder_resolution_m": {"value": 1e-6, "source": "t"}},
           "uncertainty": {"correlation": []}}
    with pytest.raises(PlantFileError) as exc:
        Plant.from_dict(doc, origin="p.toml")
    msg = str(exc.value)
    assert "correlation" in msg and "}}" not in msg and "} or an array" in msg
