"""Fit time of the EMPS record (a benchmark, not a test): median of 3 runs after a warm-up.

    python examples/emps/time_fit.py [PATH/DATA_EMPS.mat]

Prints the median wall and CPU time of ``fit_linear_axis`` (with its delay check) on the record.
"""

import statistics
import sys
import time
from pathlib import Path

from prsa_ctrl.identification.axis import fit_linear_axis, load_axis_plant
from prsa_ctrl.identification.logformat import load_axis_log, load_log_format

HERE = Path(__file__).resolve().parent


def main() -> None:
    data = sys.argv[1] if len(sys.argv) > 1 else str(HERE / "DATA_EMPS.mat")
    log = load_axis_log(data, load_log_format(HERE / "log.toml"))
    base = load_axis_plant(HERE / "plant.toml")
    fit_linear_axis([log], base)  # warm-up (imports, caches)
    wall, cpu = [], []
    for _ in range(3):
        w0, c0 = time.perf_counter(), time.process_time()
        fit = fit_linear_axis([log], base)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    print(f"fit_linear_axis on {Path(data).name} ({log.n} samples): median wall {statistics.median(wall):.2f} s "
          f"{[round(x, 2) for x in wall]}, median CPU {statistics.median(cpu):.2f} s {[round(x, 2) for x in cpu]}; "
          f"{fit.iterations} replays in the main fit")


if __name__ == "__main__":
    main()
