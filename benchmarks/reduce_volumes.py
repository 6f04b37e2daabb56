"""Where a reduced run's terrain departs from NDEM's: the volume its cut lost and its pile gained.

    python benchmarks/reduce_volumes.py --results results [--config config/config.yaml] \\
        [--dynamics replay ridge unet persistence]

For each held-out point of the config, the final surfaces of NDEM's run, its twin (NDEM from
the bed moved 1 µm) and each dynamics model's reduced run, smoothed at one grain diameter on
the comparison's lattice (``compare.smoothed_surface``), are set against the bed's: the volume
below the bed's surface (what the cut lost, m³), the volume above it (what the piles gained,
m³) and their ratio, the material's bulking. NDEM's loose pile holds more than its cut gave
up; a loop whose pile is packed tighter, or lower where its grains cannot rise, holds less for
the same cut. Beside them each run's smoothed-surface accuracy against NDEM. Reads
``--results`` only.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.reduce.compare import height_accuracy, smoothed_surface, surface_sigma
from dozerlab.scenarios.bed import Bed


def cut_and_pile(h: np.ndarray, h_bed: np.ndarray, cell_area: float) -> tuple[float, float]:
    """The volume (m³) below and above the bed's surface ``h_bed`` of the surface ``h``, both
    (Nx, Ny) m on cells of ``cell_area`` m²."""
    d = h - h_bed
    return float(-np.clip(d, None, 0.0).sum() * cell_area), float(
        np.clip(d, 0.0, None).sum() * cell_area
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--dynamics", nargs="+", default=["replay", "ridge", "unet", "persistence"])
    args = ap.parse_args()
    cfg = load_config(args.config)
    res = args.results
    print("point / run: cut lost m³, pile gained m³, pile / cut, smoothed-surface accuracy")
    for pt in (p for p in P.sweep_points(cfg) if p.role != "train"):
        bed = Bed.load(P.bed_path(res, pt.scenario))
        sigma = surface_sigma(bed.radii)

        def surface(path: Path, bed: Bed = bed, sigma: float = sigma) -> np.ndarray:
            positions = Bed.load(path).positions
            return smoothed_surface(positions, bed.radii, bed.length, bed.width, sigma)

        h_bed = smoothed_surface(bed.positions, bed.radii, bed.length, bed.width, sigma)
        area = bed.length * bed.width / h_bed.size
        runs = {"ndem": P.state_path(res, pt), "twin": P.twin_path(res, pt, "npz")} | {
            m: P.reduced_path(res, m, pt, "npz") for m in args.dynamics
        }
        h_ndem = surface(runs["ndem"])
        print(f"{pt.scenario} {pt.name} ({pt.role})")
        for name, path in runs.items():
            if not path.exists():
                print(f"    {name:12s} no run at {path}")
                continue
            h = surface(path)
            cut, pile = cut_and_pile(h, h_bed, area)
            acc = height_accuracy(h, h_ndem, h_bed)
            print(f"    {name:12s} {cut:.3f} {pile:.3f} {pile / cut:.2f}  {acc:.3f}")


if __name__ == "__main__":
    main()
