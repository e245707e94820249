"""prsa_ctrl.cli.tune: heavy modules stay out of a default run (the cold start is measured in
benchmarks/bench.py; here only what is deterministic: which modules get imported)."""

import subprocess
import sys

import pytest

HEAVY = ("matplotlib", "control", "scipy.optimize", "scipy.stats", "scipy.signal", "scipy.integrate", "pandas")


def _loaded_after(code: str, tmp_path) -> list[str]:
    probe = f"{code}\nimport sys\nprint(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-W", "ignore", "-c", probe], capture_output=True, text=True,
                         cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return eval(out.stdout.strip().splitlines()[-1])  # a list of names printed by the probe


def test_importing_the_command_pulls_no_heavy_module(tmp_path):
    assert _loaded_after("import prsa_ctrl.cli.tune", tmp_path) == []


@pytest.mark.slow
def test_a_default_run_pulls_no_heavy_module(tmp_path):
    """The whole default ``prsa-tune --load-step 500:1500`` (tune, verify, baselines, report):
    none of python-control, matplotlib or scipy.optimize/stats/signal/integrate is needed."""
    code = ("from prsa_ctrl.cli.tune import main\n"
            "code = main(['--load-step', '500:1500', '--quiet'])\n"
            "assert code == 0, code")
    assert _loaded_after(code, tmp_path) == []
