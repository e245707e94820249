"""Figures of a move scene (:mod:`prsa_ctrl.studies.move`): the move of each cascade design and
the hold after the load step."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from ..studies.move import following_error_m, simulate_move
from ..studies.movescene import MoveScene
from .loop import save_figure

if TYPE_CHECKING:
    from ..plant.plantfile import Plant
    from ..tuning.cascade import CascadeDesign

__all__ = ["write_move_plots"]


def write_move_plots(plant: "Plant", scene: MoveScene, designs: "list[CascadeDesign]", directory: str | Path) -> list[Path]:
    """Figures of a move scene, PNG and SVG: the move
    (position, following error, nut speed and motor torque of each design against time) and
    the hold (position deviation after the hold step, nut and screw side).

    Parameters
    ----------
    plant : Plant
    scene : MoveScene
    designs : list of CascadeDesign
        Verified designs (:func:`verify_design` keeps their runs).
    directory : str or Path
        Existing folder the files are written into.

    Returns
    -------
    list of Path
        ``move.png``, ``move.svg``, ``hold.png``, ``hold.svg``.
    """
    matplotlib.use("Agg")
    directory = Path(directory)
    m = scene.motion()
    runs = []
    for d in designs:
        r = d.run if d.run is not None else simulate_move(plant, scene, d.speed, d.position)
        runs.append((d, r))
    fig, ax = plt.subplots(4, 1, sharex=True, figsize=(7.5, 8.0), layout="constrained")
    t_end = scene.hold_step_s if scene.hold_step_n else scene.duration_s
    for n, (d, r) in enumerate(runs):
        t = np.asarray(r.time)
        unit = plant.lead_per_rad if d.position.measured == "nut_angle" else 1.0
        keep = t <= t_end
        label = f"{d.method} (Kv {d.position.kv:.3g} 1/s)"
        if n == 0:
            ax[0].plot(t[keep], r.output("position_reference")[keep] * unit * 1e3, "k--", lw=1.0, label="reference")
            ax[2].plot(t[keep], m.at(t[keep])[1] / plant.lead_per_rad, "k--", lw=1.0, label="profile")
        ax[0].plot(t[keep], r.output("position_measured")[keep] * unit * 1e3, lw=1.2, label=label)
        ax[1].plot(t[keep], following_error_m(r, plant)[keep] * 1e6, lw=1.2, label=label)
        ax[2].plot(t[keep], r.output("nut_speed")[keep], lw=1.2, label=label)
        ax[3].plot(t[keep], r.output("motor_torque")[keep], lw=1.2, label=label)
    for a_ in ax:
        a_.axvline(scene.load_at_s, color="0.6", lw=0.8, ls=":")
        a_.grid(True, alpha=0.3)
    ax[1].axhspan(-scene.window_m * 1e6, scene.window_m * 1e6, color="0.9", zorder=0)
    ax[0].set_ylabel("position (mm)")
    ax[1].set_ylabel("following error (um)")
    ax[2].set_ylabel("nut speed (rad/s)")
    ax[3].set_ylabel("motor torque (N m)")
    ax[3].axhline(plant.torque_limit, color="r", lw=0.8, ls="--")
    ax[3].set_xlabel("time (s)")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"{scene.name}: {scene.distance_m * 1e3:g} mm move at {scene.max_speed_m_s * 1e3:g} mm/s, "
                    f"{scene.load_n:g} N at {scene.load_at_s:.3g} s (dotted)", fontsize=9)
    files = save_figure(fig, directory / "move")
    plt.close(fig)
    if scene.hold_step_n:
        fig, ax = plt.subplots(1, 1, figsize=(7.5, 4.0), layout="constrained")
        for d, r in runs:
            t = np.asarray(r.time)
            keep = t >= scene.hold_step_s - 0.005
            ax.plot(t[keep], following_error_m(r, plant)[keep] * 1e6, lw=1.2,
                    label=f"{d.method}: max {d.verified.holding_deviation_m * 1e6:.3g} um" if d.verified else d.method)
        ax.axhspan(-scene.window_m * 1e6, scene.window_m * 1e6, color="0.9", zorder=0)
        ax.axvline(scene.hold_step_s, color="0.6", lw=0.8, ls=":")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("position deviation (um)")
        ax.set_title(f"holding: {scene.hold_step_n:g} N step at {scene.hold_step_s:.3g} s "
                     f"({'nut angle' if scene.measured == 'nut_angle' else 'screw position'} measured)", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        files += save_figure(fig, directory / "hold")
        plt.close(fig)
    return files
