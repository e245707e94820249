"""The two-mass linear axis's fit over seeds of the independent test generator: each key's bias (%)
and whether its truth lies inside its 95 % interval, with and without the unlogged force disturbance.

Run from the checkout's root (it imports the generator of tests/identification/test_axiscompliant.py,
one log of 3,000 samples per seed, the 2 N rms disturbance by default):

    PYTHONPATH=$PWD OPENBLAS_NUM_THREADS=1 python scripts/axis-twomass-sweep.py 1-25 2.0 > d2.jsonl
    PYTHONPATH=$PWD OPENBLAS_NUM_THREADS=1 python scripts/axis-twomass-sweep.py 1-25 0.0 > d0.jsonl

Each seed is one JSON line (``seed``, ``cpu_s`` the fit's process time, ``passes``, ``diagnosis``,
``method`` (the fit's, from its report), per key ``value``, ``bias_percent``, ``inside``: true, false, or null for a key held and not
fitted; or ``failed`` with the fit's error); the summary on stderr: per key the seeds whose interval
holds the truth, of those fitted, and the mean and median bias of the converged fits.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "tests" / "identification"), str(ROOT / "tests")]


def seeds(text: str) -> list[int]:
    """``"1-25"`` or ``"1,4,7"`` as a list of seeds."""
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in text.split(",")]


def main(argv: list[str]) -> int:
    import test_axiscompliant as gen  # the independent two-mass generator
    from prsa_ctrl.errors import AxisFitError
    from prsa_ctrl.identification.axiscompliant import TWO_MASS_PARAMETERS, fit_two_mass_axis

    which = seeds(argv[0]) if argv else list(range(1, 26))
    noise = float(argv[1]) if len(argv) > 1 else 2.0
    truth = gen._truth_vector()
    rows = []
    for s in which:
        log = gen._log(s, noise_n=noise)
        t0 = time.process_time()
        try:
            fit = fit_two_mass_axis([log], gen._base(log))
        except AxisFitError as exc:
            row = {"seed": s, "noise_n": noise, "failed": str(exc)}
        else:
            row = {"seed": s, "noise_n": noise, "cpu_s": time.process_time() - t0, "passes": fit.passes,
                   "diagnosis": fit.validation.get("diagnosis"), "method": fit.as_dict()["method"].split(";")[0], "keys": {}}
            for k in TWO_MASS_PARAMETERS:
                e = fit.parameters[k]
                ci = e["ci95"]
                row["keys"][k] = {"value": e["value"], "bias_percent": 100 * (e["value"] / truth[k] - 1),
                                  "inside": None if ci is None else bool(ci[0] <= truth[k] <= ci[1])}
        rows.append(row)
        print(json.dumps(row), flush=True)
    done = [r for r in rows if "keys" in r]
    print(f"seeds {which[0]}..{which[-1]}, disturbance {noise:g} N rms: {len(done)} converged of {len(rows)}, "
          f"{sum(r['passes'] for r in done)} pass their validation", file=sys.stderr)
    for k in TWO_MASS_PARAMETERS:
        fitted = [r["keys"][k] for r in done if r["keys"][k]["inside"] is not None]
        b = [x["bias_percent"] for x in fitted]
        if b:
            print(f"  {k}: truth inside {sum(x['inside'] for x in fitted)} of {len(fitted)}; bias mean "
                  f"{statistics.mean(b):+.2f} %, median {statistics.median(b):+.2f} %", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
