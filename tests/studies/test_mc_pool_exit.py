"""The process-pool Monte Carlo leaves nothing running once it has returned.

A finished run used ``ProcessPoolExecutor.shutdown(wait=False)``: the pool's management thread
and workers were still alive when ``run_monte_carlo`` returned, and at interpreter exit they
raced with ``threading._shutdown`` ("Exception ignored ... Bad file descriptor" printed after a
successful ``prsa-tune --monte-carlo`` in about a quarter of the runs). The check here is
deterministic: right after the call, no pool thread and no worker process may be left.
"""

from __future__ import annotations

import multiprocessing
import threading
import warnings

from prsa_ctrl.drive.pid import PID
from prsa_ctrl.plant import load_plant
from prsa_ctrl.studies import montecarlo as mc
from prsa_ctrl.studies.scene import load_scene


def test_finished_process_pool_run_leaves_no_thread_and_no_worker():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = load_plant()
    scene = load_scene("robust-load-step")
    before = {t.ident for t in threading.enumerate()}
    rep = mc.run_monte_carlo(plant, scene, {"design": PID(0.0849, 14.67, tf=1e-3)}, 4, seed=2, backend="process",
                             workers=2, chunk=2, quiet=True, progress=False, spec={})
    assert rep.samples["metrics"].shape[0] == 4
    left = [t for t in threading.enumerate() if t.ident not in before and t.is_alive()]
    assert left == [], f"pool threads still running after the run: {[t.name for t in left]}"
    assert multiprocessing.active_children() == []
