"""Settled beds left at rest under NDEM settings side by side: what spins, what creeps, what the
active zone keeps awake.

    NUMBA_NUM_THREADS=2 python benchmarks/ndem_rest.py \\
        "free:" "spin:material.spinning_resistance=0.1" \\
        "zone:solver.active_zone.enabled=true" \\
        "zone+spin:solver.active_zone.enabled=true,material.spinning_resistance=0.1" \\
        --config config/config.yaml \\
        --beds results/beds/hill.npz results/beds/step.npz results/beds/trench.npz

Each variant is ``NAME:KEY=VALUE,...`` (dotted config keys, values as YAML) over ``--config``,
validated like it. Each bed goes into a world as the workflow's runs build it
(``scenarios.build.make_world``: walls, ground, the bed's velocities, its still grains counted
as rested), with no blade, and steps ``--seconds`` of simulated time under each variant in
turn. Prints per bed how many grains spin faster than ``--spin-speed`` at their surface (|ω|·r) in
the bed file, then per variant: wall seconds per simulated second (the first step, which loads
numba's cached kernels, not counted), the solver's sweeps a step (over the run and its second
half, once the bed's multipliers are warm), the fastest grain at the end, the grains still
spinning that fast at the end, the grains moved more than 1 mm and the median displacement, the
change of the mean and top surface (the grains' tops per 5 cm cell), and with the active zone
the grains awake after the first step, at the end and on average. NDEM is deterministic for a
given thread count, so the counts repeat; the seconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dozerlab.config import load_config
from dozerlab.scenarios.bed import Bed
from dozerlab.scenarios.build import make_world
from reduce_settings import variant

CELL = 0.05  # m, the surface's cells


def surface(positions: np.ndarray, radii: np.ndarray) -> tuple[float, float]:
    """The mean and the highest of the grains' tops per ``CELL`` × ``CELL`` column (m)."""
    cells = np.floor(positions[:, :2] / CELL).astype(np.int64)
    _, column = np.unique(cells, axis=0, return_inverse=True)
    tops = np.full(column.max() + 1, -np.inf)
    np.maximum.at(tops, column.ravel(), positions[:, 2] + radii)
    return float(tops.mean()), float(tops.max())


def rest(bed: Bed, config: dict, seconds: float, spin_speed: float) -> str:
    """One bed at rest for ``seconds`` under ``config``: the variant's line of figures."""
    world, _ = make_world(bed, config)
    zone = config["solver"]["active_zone"]["enabled"]
    steps = max(2, round(seconds / world.dt))
    x0 = world.positions.copy()
    mean0, top0 = surface(x0, bed.radii)
    awake = []
    sweeps = []
    for i in range(steps):
        if i == 1:
            t0 = time.perf_counter()
        sweeps.append(world.step().iterations)
        awake.append(int(world.state.awake.sum()))
    wall = (time.perf_counter() - t0) / ((steps - 1) * world.dt)
    spin = np.linalg.norm(world.angular_velocities, axis=1) * bed.radii
    shift = np.linalg.norm(world.positions - x0, axis=1)
    mean, top = surface(world.positions, bed.radii)
    fastest = float(np.linalg.norm(world.velocities, axis=1).max())
    line = (
        f"{wall:6.2f} s per simulated s, {np.mean(sweeps):4.1f} sweeps a step "
        f"({np.mean(sweeps[steps // 2 :]):4.1f} in the second half); fastest grain at the end "
        f"{fastest:.3f} m/s; spinning {int((spin > spin_speed).sum()):3d} "
        f"(fastest {spin.max():.3f} m/s); moved > 1 mm {int((shift > 1e-3).sum()):3d}, median "
        f"{1e6 * float(np.median(shift)):5.1f} µm; surface {1e3 * (mean - mean0):+.2f} / "
        f"{1e3 * (top - top0):+.2f} mm"
    )
    if zone:
        line += (
            f"; awake {awake[0]} after a step, {awake[-1]} at the end, {np.mean(awake):.0f} mean"
        )
    return line


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variants", nargs="+", help="NAME:KEY=VALUE,... over --config")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--beds", nargs="+", required=True, help="bed files (.npz)")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated s at rest")
    ap.add_argument(
        "--spin-speed", type=float, default=0.02, help="m/s at the surface counted as spinning"
    )
    args = ap.parse_args(argv)
    base = load_config(args.config)
    variants = [variant(text, base) for text in args.variants]
    for path in args.beds:
        bed = Bed.load(path)
        spin = np.linalg.norm(bed.angular_velocities, axis=1) * bed.radii
        print(
            f"{path}: {len(bed.radii)} grains, {int((spin > args.spin_speed).sum())} spinning "
            f"faster than {args.spin_speed} m/s at the surface (fastest {spin.max():.3f} m/s)",
            flush=True,
        )
        for name, cfg in variants:
            print(f"  {name:12s} {rest(bed, cfg, args.seconds, args.spin_speed)}", flush=True)


if __name__ == "__main__":
    main()
