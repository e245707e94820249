"""``python -m prsa_ctrl.cli.montecarlo``: replay one sample of a Monte-Carlo verification
(:func:`prsa_ctrl.studies.montecarlo.replay_sample`), the command each report's worst sample
names; prints the sample's parameters and metrics as JSON (exit 0), or one line (exit 2)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

from ..drive.pid import PID
from ..errors import PlantFileError, SceneError
from ..io.output import json_safe
from ..plant.plantfile import load_plant
from ..studies.montecarlo import INTEGRATOR_CHOICES, replay_sample
from ..studies.scene import load_scene, require_speed_scene
from .common import EXIT_BAD_INPUT, EXIT_OK, echo

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m prsa_ctrl.cli.montecarlo``: replay one Monte-Carlo sample of one design."""
    ap = argparse.ArgumentParser(prog="python -m prsa_ctrl.cli.montecarlo", description=main.__doc__)
    ap.add_argument("--plant", default=None)
    ap.add_argument("--scene", default="robust-load-step")
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--index", type=int, required=True)
    ap.add_argument("--integrator", choices=INTEGRATOR_CHOICES, default="auto",
                    help="the run's integrator choice (its replay command names it)")
    for g in ("kp", "ki", "kd", "tf", "kff"):
        ap.add_argument(f"--{g}", type=float, default=0.0 if g in ("kd", "kff") else None, required=g in ("kp", "ki"))
    a = ap.parse_args(argv)
    try:
        plant, scene = load_plant(a.plant), require_speed_scene(load_scene(a.scene))
        kw = {"tf": a.tf} if a.tf else {}
        pid = PID(a.kp, a.ki, a.kd, kff=a.kff, **kw)
        if a.seed < 0 or a.index < 0:
            raise ValueError(f"--seed {a.seed} --index {a.index}; expected integers >= 0")
        out = replay_sample(plant, scene, pid, a.seed, a.index, a.integrator)
    except (PlantFileError, SceneError, ValueError) as exc:
        echo(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    echo(json.dumps(json_safe(out), indent=2))
    return EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
