"""The report's material for each sweep point: its numbers (sweep table row) and its figures.

Figures are drawn by the layers that own them (``dozerlab.fields.plots`` for field slices and
force series; the trajectory PNGs ``dozerlab trajectory`` wrote) and embedded here. A point whose
outputs are missing gets a row that says so instead of failing the report, so the report of a
partial run still shows what exists.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dozerlab.report import html
from dozerlab.sweep import SweepPoint, field_path, trajectory_path


@dataclass
class PointSummary:
    """The numbers of one sweep point; None where an output is missing.

    ``steps`` counts solver steps, ``simulated`` is the simulated time in s, ``wall_time`` the
    wall-clock time in s of the simulation's stepping loop (the store's ``wall_time_s``
    attribute; None for stores written before it existed); ``mean_force`` / ``peak_force`` are
    the mean and largest blade force magnitude |F| in N, ``peak_time`` when the largest was
    reached, in s.
    """

    point: SweepPoint
    built: bool = False
    particles: int | None = None
    steps: int | None = None
    simulated: float | None = None
    wall_time: float | None = None
    mean_force: float | None = None
    peak_force: float | None = None
    peak_time: float | None = None

    @property
    def slowdown(self) -> float | None:
        """Wall time per simulated time (1 = real time), None when either is unknown."""
        if self.wall_time is None or not self.simulated:
            return None
        return self.wall_time / self.simulated


def summarize(results: str | Path, point: SweepPoint) -> PointSummary:
    """The numbers of ``point`` from its field store."""
    from dozerlab.fields.store import open_store

    summary = PointSummary(point)
    store = field_path(results, point)
    if not store.exists():
        return summary
    ds = open_store(store)
    force = np.linalg.norm(ds["force"].values, axis=1)
    summary.built = True
    summary.particles = int(ds.attrs["particle_count"])
    summary.steps = int(ds.sizes["time"]) * int(ds.attrs.get("sample_every") or 1)
    summary.simulated = float(ds["time"].values[-1]) if ds.sizes["time"] else 0.0
    if ds.attrs.get("wall_time_s") is not None:
        summary.wall_time = float(ds.attrs["wall_time_s"])
    if force.size:
        peak = int(force.argmax())
        summary.mean_force, summary.peak_force = float(force.mean()), float(force[peak])
        summary.peak_time = float(ds["time"].values[peak])
    return summary


def point_figures(results: str | Path, point: SweepPoint) -> list[str]:
    """Embedded figures of one point: trajectory, the mid-run field slice, force series."""
    out = []
    traj_png = trajectory_path(results, point, "png")
    if traj_png.is_file():
        out.append(html.figure(traj_png, f"{point.scenario} {point.name}: blade trajectory"))
    store = field_path(results, point)
    if store.exists():
        from dozerlab.fields.plots import plot_force, plot_slice
        from dozerlab.fields.store import open_store

        ds = open_store(store)
        with tempfile.TemporaryDirectory() as tmp:
            if ds.sizes["time"]:
                mid = ds.sizes["time"] // 2
                png = plot_slice(ds, mid, Path(tmp) / "slice.png")
                t = float(ds["time"].values[mid])
                out.append(
                    html.figure(
                        png,
                        f"{point.scenario} {point.name}: density (kg/m³) and velocity relative to "
                        f"the blade in the middle y-slice, t = {t:.2f} s",
                    )
                )
            png = plot_force(ds, Path(tmp) / "force.png")
            out.append(
                html.figure(
                    png,
                    f"{point.scenario} {point.name}: blade force (kN) and torque about the tip "
                    "(kN·m)",
                )
            )
    return out
