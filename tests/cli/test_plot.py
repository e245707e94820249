"""prsa_ctrl.cli.plot (prsa-plot): the figures of a PID on the paper plant, written as PNG files
with the margins printed; unstable gains plotted (frequency plots only) with a warning, not refused.
(The frequency unit of its loop Bode figure: tests/plots/test_loop.py.)"""

import matplotlib.pyplot as plt
import pytest

from prsa_ctrl.cli.plot import plot_main


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def test_prsa_plot_command(tmp_path, capsys):
    rc = plot_main(["--kp", "0.085", "--ki", "14.7", "--out", str(tmp_path)])
    assert rc == 0
    names = {p.stem for p in tmp_path.glob("*.png")}
    assert names == {"plant_bode", "loop_bode", "sensitivity", "load_step", "setpoint_step"}
    out = capsys.readouterr().out
    assert "Margins: Ms 1.4" in out
    assert "crossover" in out
    # Unstable gains are plotted with a warning (frequency plots only), not refused.
    assert plot_main(["--kp", "50", "--ki", "1", "--out", str(tmp_path / "x")]) == 0
    assert "UNSTABLE" in capsys.readouterr().out
    assert {p.stem for p in (tmp_path / "x").glob("*.png")} == {"plant_bode", "loop_bode", "sensitivity"}
