"""The smoothed surface a grid-level reduced mode could reach at best: the terrain rebuilt from
NDEM's own density fields, no grain moved.

    python benchmarks/grid_surface.py --results results [--config config/config.yaml]

A grid-level mode would carry the material in the sampling volume as a density field and leave
the terrain behind as columns of packed grains. This rebuilds the final terrain that way from
the best fields there are, each held-out point's NDEM store: the bed's surface (the spheres'
tops on the comparison's lattice of a quarter grain diameter), and over it, row by row, every
lattice cell under the volume takes the height of its column, the volume's floor plus the
column's mass per area over a packed density; what the last row covers is the final pile. The
packed density is the bed's own: its mass over the volume under its surface.
Prints, per held-out point, the twin's smoothed-surface accuracy (NDEM from the bed moved 1 µm),
this terrain's and its skill (accuracy over the twin's), at the bed's packed density and at 0.9
and 1.1 times it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import open_store
from dozerlab.reduce.compare import (
    gaussian_smooth,
    height_accuracy,
    smoothed_surface,
    surface_sigma,
)
from dozerlab.scenarios.bed import Bed
from dozerlab.scenarios.heightfield import height_field


def column_terrain(
    bed: Bed, grid: SamplingGrid, density: np.ndarray, tips: np.ndarray, packed: float, cell: float
) -> np.ndarray:
    """The final terrain (Nx, Ny) m on a lattice of ``cell`` m: the bed's surface, each cell
    under the volume at a row (tip ``tips`` (T, 3) m) set to its column's height from
    ``density`` (T, Nx, Ny, Nz) kg/m³ over ``packed`` kg/m³."""
    nx, ny = round(bed.length / cell), round(bed.width / cell)
    _, h = height_field(bed.positions, bed.radii, bed.length, bed.width, (nx, ny))
    xc = (np.arange(nx) + 0.5) * bed.length / nx
    yc = -bed.width / 2 + (np.arange(ny) + 0.5) * bed.width / ny
    size, lower = np.asarray(grid.bin_size), np.asarray(grid.lower)
    for rho, tip in zip(density, tips, strict=True):
        lo = tip + lower
        ix = np.floor((xc - lo[0]) / size[0]).astype(int)
        iy = np.floor((yc - lo[1]) / size[1]).astype(int)
        cx = np.flatnonzero((ix >= 0) & (ix < grid.bins[0]))
        cy = np.flatnonzero((iy >= 0) & (iy < grid.bins[1]))
        column = lo[2] + rho.sum(axis=2) * size[2] / packed
        h[np.ix_(cx, cy)] = column[np.ix_(ix[cx], iy[cy])]
    return h


def packed_density(bed: Bed, cell: float) -> float:
    """The bed's packed density (kg/m³): its mass over the volume under its surface."""
    nx, ny = round(bed.length / cell), round(bed.width / cell)
    _, h = height_field(bed.positions, bed.radii, bed.length, bed.width, (nx, ny))
    return float(bed.masses.sum() / (h.sum() * bed.length * bed.width / (nx * ny)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results")
    ap.add_argument("--config", default="config/config.yaml")
    args = ap.parse_args()
    cfg = load_config(args.config)
    grid = SamplingGrid.from_config(cfg)
    res = Path(args.results)
    for point in (p for p in P.sweep_points(cfg) if p.role != "train"):
        bed = Bed.load(P.bed_path(res, point.scenario))
        ndem = Bed.load(P.state_path(res, point))
        twin = Bed.load(P.twin_path(res, point, "npz"))
        store = open_store(P.field_path(res, point))
        density, tips = store["density"].values, store["blade_position"].values.astype(float)
        sigma = surface_sigma(bed.radii)
        cell = sigma / 4.0

        def surface(b: Bed, sigma: float = sigma) -> np.ndarray:
            return smoothed_surface(b.positions, b.radii, b.length, b.width, sigma)

        s_bed, s_ndem = surface(bed), surface(ndem)
        twin_acc = height_accuracy(surface(twin), s_ndem, s_bed)
        packed = packed_density(bed, cell)
        figures = []
        for f in (1.0, 0.9, 1.1):
            h = column_terrain(bed, grid, density, tips, f * packed, cell)
            acc = height_accuracy(gaussian_smooth(h, sigma / cell), s_ndem, s_bed)
            figures.append(f"{f:.1f}x: {acc:.3f} (skill {acc / twin_acc:.3f})")
        print(
            f"{point.scenario} {point.name} ({point.role}): twin {twin_acc:.3f}; packed density "
            f"{packed:.0f} kg/m3; NDEM's density columns at " + ", ".join(figures),
            flush=True,
        )


if __name__ == "__main__":
    main()
