"""Figures of beds and trajectories (after the thesis's figures 3.3–3.8), PNG via matplotlib Agg."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dozerlab.runtime import OutputKind, atomic_output, marked_png, png_metadata

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure

    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory


#: ``bed --plot`` and ``trajectory --plot``: each replaces only a figure of its own command.
BED_PLOT = marked_png("a dozerlab bed figure (bed --plot)", "bed-plot")
TRAJECTORY_PLOT = marked_png("a dozerlab trajectory figure (trajectory --plot)", "trajectory-plot")


def _save(fig, path: str | Path, kind: OutputKind) -> None:
    with atomic_output(path, kind) as tmp:
        fig.savefig(tmp, format="png", dpi=120, metadata=png_metadata(kind.name))


def plot_trajectory(traj: Trajectory, path: str | Path) -> None:
    """Write a PNG of the planned path: the raw and filtered height profile (thesis fig. 3.5–3.6),
    the tip trajectory over the filtered bed (fig. 3.7) and the velocity components (fig. 3.8)."""
    from matplotlib.figure import Figure

    # the object API, not pyplot: importing pyplot was a third of a trajectory job
    fig = Figure(figsize=(9, 10))
    axes = fig.subplots(3, 1, sharex=True)
    ax = axes[0]
    if traj.height_x.size:
        ax.plot(traj.height_x, traj.height_raw, lw=0.7, color="0.55", label="height field (raw)")
        ax.plot(traj.height_x, traj.height_filtered, lw=1.6, color="C0", label="filtered")
    ax.set_ylabel("z (m)")
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
    ax.set_ylabel("z (m)")
    ax.set_title(
        f"trajectory: speed {traj.speed:g} m/s, cut depth {traj.depth:g} m, {traj.steps} steps"
    )
    ax.legend(loc="upper right")

    ax = axes[2]
    x = traj.position[:-1, 0]
    for k, name in enumerate("xyz"):
        ax.plot(x, traj.velocity[:, k], lw=1.2, label=f"v{name}")
    ax.plot(x, np.linalg.norm(traj.velocity, axis=1), lw=0.8, ls=":", color="k", label="|v|")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("velocity (m/s)")
    ax.legend(loc="upper right")
    fig.tight_layout()
    _save(fig, path, TRAJECTORY_PLOT)


def bed_figure(bed: Bed) -> Figure:
    """A matplotlib figure of a bed: side view with every particle drawn to scale as a disc
    coloured by its y (thesis fig. 3.3–3.4), the bed's surface height seen from above, and the
    settle log (kinetic energy per particle and contacts solved over time)."""
    from matplotlib.collections import EllipseCollection
    from matplotlib.figure import Figure

    from dozerlab.scenarios.heightfield import height_field

    pos, diameter = bed.positions, 2.0 * bed.radii
    top = float((pos[:, 2] + bed.radii).max()) if bed.count else 1.0
    width_in = 12.0
    # axes heights follow the bed's aspect so that both views keep x, y and z to scale
    side_h, plan_h = (
        max(1.2, width_in * 0.8 * top / bed.length),
        width_in * 0.8 * bed.width / bed.length,
    )
    fig = Figure(figsize=(width_in, side_h + plan_h + 3.4), layout="constrained")
    grid = fig.add_gridspec(3, 1, height_ratios=[side_h, plan_h, 2.2])

    ax = fig.add_subplot(grid[0])
    order = np.argsort(-pos[:, 1])  # the viewer is at y → −∞: the nearest particles last
    discs = EllipseCollection(
        diameter[order],
        diameter[order],
        np.zeros(bed.count),
        units="xy",
        offsets=pos[order][:, [0, 2]],
        offset_transform=ax.transData,
        array=pos[order, 1],
        cmap="viridis",
        edgecolors="0.15",
        linewidths=0.15,
    )
    discs.set_clim(-bed.width / 2, bed.width / 2)
    ax.add_collection(discs)
    _colorbar(fig, ax, discs, "y (m)")
    ax.set(xlim=(0, bed.length), ylim=(0, top * 1.05), aspect="equal", ylabel="z (m)")
    ax.set_title(
        f"{bed.scenario} bed: {bed.count} particles, radius {bed.radii.mean():.3g} m "
        "(side view, drawn to scale)"
    )

    ax = fig.add_subplot(grid[1])
    r = float(bed.radii.mean()) if bed.count else 0.05
    cells = (
        max(1, round(bed.length / (2 * r))),
        max(1, round(bed.width / (2 * r))),
    )  # a grain each
    _, h = height_field(pos, bed.radii, bed.length, bed.width, cells)
    im = ax.imshow(
        h.T,
        origin="lower",
        extent=(0, bed.length, -bed.width / 2, bed.width / 2),
        cmap="YlOrBr",
        vmin=0.0,
        interpolation="nearest",
    )
    _colorbar(fig, ax, im, "surface height (m)")
    ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)", title="surface height, top view")

    ax = fig.add_subplot(grid[2])
    if bed.settle_time.size:
        ax.semilogy(bed.settle_time, np.maximum(bed.settle_kinetic_energy, 1e-12), color="C0")
        ax.set_ylabel("kinetic energy\nper particle (J)", color="C0")
        twin = ax.twinx()
        twin.plot(bed.settle_time, bed.settle_contacts, color="C1", lw=0.8)
        # while the pour sleeps the grains at rest (bed.active_zone) only the awake ones' count
        twin.set_ylabel("contacts solved", color="C1")
    ax.set(xlabel="time (s)", title="build and settle log")
    return fig


def _colorbar(fig: Figure, ax: Axes, mappable: ScalarMappable, label: str) -> None:
    # beside the axes' drawn box: an equal-aspect axes is narrower than its layout slot
    cax = ax.inset_axes((1.015, 0.0, 0.015, 1.0))
    fig.colorbar(mappable, cax=cax, label=label)


def plot_bed(bed: Bed, path: str | Path) -> None:
    """Write :func:`bed_figure` of a bed as a PNG."""
    _save(bed_figure(bed), path, BED_PLOT)
