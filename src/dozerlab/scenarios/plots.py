"""Figures of beds and trajectories (after the thesis's figures 3.3–3.8), PNG via matplotlib Agg."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dozerlab.runtime import FIGURE, atomic_output, png_metadata

if TYPE_CHECKING:
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> None:
    with atomic_output(path, FIGURE) as tmp:
        fig.savefig(tmp, format="png", dpi=120, metadata=png_metadata())


def plot_trajectory(traj: Trajectory, path: str | Path) -> None:
    """Write a PNG of the planned path: the raw and filtered height profile (thesis fig. 3.5–3.6),
    the tip trajectory over the filtered bed (fig. 3.7) and the velocity components (fig. 3.8)."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(9, 10), sharex=True)
    ax = axes[0]
    if traj.height_x.size:
        ax.plot(traj.height_x, traj.height_raw, lw=0.7, color="0.55", label="height field (raw)")
        ax.plot(traj.height_x, traj.height_filtered, lw=1.6, color="C0", label="filtered")
    ax.set_ylabel("z [m]")
    ax.set_title(f"{traj.scenario or 'bed'} height profile")
    ax.legend(loc="upper right")

    ax = axes[1]
    if traj.height_x.size:
        ax.fill_between(
            traj.height_x, 0, traj.height_filtered, color="tan", alpha=0.6, label="filtered bed"
        )
    if np.isfinite(traj.goal_height):
        ax.axhline(
            traj.goal_height,
            ls="--",
            color="k",
            lw=0.8,
            label=f"goal height {traj.goal_height:g} m",
        )
    ax.plot(traj.position[:, 0], traj.position[:, 2], color="C3", lw=1.4, label="blade tip")
    ax.set_ylabel("z [m]")
    ax.set_title(
        f"trajectory: speed {traj.speed:g} m/s, cut depth {traj.depth:g} m, {traj.steps} steps"
    )
    ax.legend(loc="upper right")

    ax = axes[2]
    x = traj.position[:-1, 0]
    for k, name in enumerate("xyz"):
        ax.plot(x, traj.velocity[:, k], lw=1.2, label=f"v{name}")
    ax.plot(x, np.linalg.norm(traj.velocity, axis=1), lw=0.8, ls=":", color="k", label="|v|")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("velocity [m/s]")
    ax.legend(loc="upper right")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def plot_bed(bed: Bed, path: str | Path) -> None:
    """Write a PNG of a bed: side view of the particles (thesis fig. 3.3–3.4), top view coloured by
    height, and the settle log (kinetic energy per particle and contacts over time)."""
    plt = _pyplot()
    fig = plt.figure(figsize=(10, 9))
    grid = fig.add_gridspec(3, 1, height_ratios=[1.2, 1.0, 0.8])
    order = np.argsort(bed.positions[:, 1])
    pos = bed.positions[order]
    ax = fig.add_subplot(grid[0])
    ax.scatter(pos[:, 0], pos[:, 2], s=4, c=pos[:, 1], cmap="viridis")
    ax.set_aspect("equal")
    ax.set_xlim(0, bed.length)
    ax.set_ylim(bottom=0)
    ax.set_ylabel("z [m]")
    ax.set_title(f"{bed.scenario} bed: {bed.count} particles (side view, colour = y)")

    ax = fig.add_subplot(grid[1])
    top = np.argsort(bed.positions[:, 2])
    sc = ax.scatter(
        bed.positions[top, 0], bed.positions[top, 1], s=4, c=bed.positions[top, 2], cmap="terrain"
    )
    fig.colorbar(sc, ax=ax, label="z [m]")
    ax.set_aspect("equal")
    ax.set_xlim(0, bed.length)
    ax.set_ylim(-bed.width / 2, bed.width / 2)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")

    ax = fig.add_subplot(grid[2])
    if bed.settle_time.size:
        ax.semilogy(bed.settle_time, np.maximum(bed.settle_kinetic_energy, 1e-12), color="C0")
        ax.set_ylabel("KE per particle [J]", color="C0")
        twin = ax.twinx()
        twin.plot(bed.settle_time, bed.settle_contacts, color="C1", lw=0.8)
        twin.set_ylabel("contacts", color="C1")
    ax.set_xlabel("time [s]")
    ax.set_title("build and settle log")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
