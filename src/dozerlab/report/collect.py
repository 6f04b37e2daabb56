"""The report's material for each sweep point: its numbers (sweep table row) and its figures.

Figures are drawn by the layers that own them (``dozerlab.fields.plots`` for field slices and
force series; the trajectory PNGs ``dozerlab trajectory`` wrote) and embedded here, never
redrawn. A point whose outputs are missing gets a row that says so instead of failing the
report, so the report of a partial run still shows what exists.
"""

from __future__ import annotations

import csv
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dozerlab.report import html
from dozerlab.sweep import (
    SweepPoint,
    field_path,
    fmt_number,
    simulate_benchmark_path,
    trajectory_path,
)


@dataclass
class PointSummary:
    """The sweep-table row of one point; None where an output is missing.

    ``wall_time`` is the simulation job's wall-clock time in s (Snakemake's benchmark record);
    ``mean_force`` / ``peak_force`` are the mean and largest blade force magnitude |F| in N.
    """

    point: SweepPoint
    particles: int | None = None
    steps: int | None = None
    wall_time: float | None = None
    mean_force: float | None = None
    peak_force: float | None = None

    def row(self) -> list[object]:
        p = self.point
        return [
            p.scenario,
            p.role,
            fmt_number(p.speed),
            fmt_number(p.depth),
            self.particles,
            self.steps,
            self.wall_time,
            self.mean_force,
            self.peak_force,
        ]


HEADERS = [
    "scenario",
    "role",
    "speed (m/s)",
    "depth (m)",
    "particles",
    "steps",
    "wall time (s)",
    "mean |F| (N)",
    "peak |F| (N)",
]


def wall_time(results: str | Path, point: SweepPoint) -> float | None:
    """The simulation job's wall time in s from Snakemake's benchmark TSV (None if absent)."""
    path = simulate_benchmark_path(results, point)
    if not path.is_file():
        return None
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    return float(rows[-1]["s"]) if rows and rows[-1].get("s") else None


def summarize(results: str | Path, point: SweepPoint) -> PointSummary:
    """The sweep-table numbers of ``point`` from its field store and benchmark record."""
    from dozerlab.fields.store import open_store

    summary = PointSummary(point, wall_time=wall_time(results, point))
    store = field_path(results, point)
    if not store.exists():
        return summary
    ds = open_store(store)
    force = np.linalg.norm(ds["force"].values, axis=1)
    summary.particles = int(ds.attrs["particle_count"])
    summary.steps = int(ds.sizes["time"]) * int(ds.attrs.get("sample_every") or 1)
    if force.size:
        summary.mean_force, summary.peak_force = float(force.mean()), float(force.max())
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
                        png, f"{point.scenario} {point.name}: density and velocity, t = {t:.2f} s"
                    )
                )
            png = plot_force(ds, Path(tmp) / "force.png")
            out.append(html.figure(png, f"{point.scenario} {point.name}: blade force and torque"))
    if not out:
        out.append(
            f'<p class="missing">{html.esc(point.scenario)} {html.esc(point.name)}: not built yet</p>'
        )
    return out
