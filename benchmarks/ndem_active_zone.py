"""NDEM's active zone against the full solve and against NDEM's own chaos, side by side.

For each point, three runs of the simulate loop on the same bed, thread count and machine:
the full solve, its twin (the full solve from the bed with every grain moved a seeded 1 µm:
NDEM's run-to-run spread) and the active zone. Printed per point: wall time per simulated
second of each, the zone's speed-up over the full solve, and how far the twin and the zone land
from the full run on the scales NDEM reproduces — the pushing force low-passed over 0.1 s
(relative RMSE, and the error of its mean over the pass) and the final surface smoothed at one
grain diameter (accuracy 1 − Σ|h − h_full| / Σ|h_full − h_bed|). The zone passes where it is at
least as close to the full run as the twin is.

    python benchmarks/ndem_active_zone.py --results results --configfile config/config.yaml
    python benchmarks/ndem_active_zone.py --points hill:0.875:0.045 --threads 1

The beds and trajectories come from a workflow's results folder (``snakemake --cores 2
results/trajectories/...``); the default points are the config's held-out ones. Not a test:
the times depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def run(bed: Any, traj: Any, config: dict[str, Any], tmp: Path, name: str) -> dict[str, Any]:
    """One simulate loop; its loop wall time (s), force rows (T, 3) N, row period (s) and final
    positions (N, 3) m."""
    from dozerlab.fields.run import drive
    from dozerlab.fields.sampling import SamplingGrid
    from dozerlab.scenarios.bed import Bed

    grid = SamplingGrid.from_config(config)
    attrs = {"scenario": bed.scenario, "speed": traj.speed, "depth": None}
    state = tmp / f"{name}.npz"
    t0 = time.perf_counter()
    stats = drive(bed, traj, config, grid, attrs, tmp / f"{name}.zarr", state_out=state)
    wall = time.perf_counter() - t0
    every = int(config["sampling"]["every"])
    return {
        "loop_s": stats.wall_time,
        "wall_s": wall,
        "force": np.array(stats.forces).reshape(-1, 3),
        "row_dt": every * traj.dt,
        "positions": Bed.load(state).positions,
        "active_fraction": stats.metrics(bed.count)["active_fraction"],
    }


def agreement(a: dict[str, Any], ref: dict[str, Any], bed: Any, sigma: float) -> dict[str, float]:
    """How close run ``a`` lands to ``ref`` on the force low-passed over 0.1 s and the surface
    smoothed at ``sigma`` (m)."""
    from dozerlab.reduce.compare import height_accuracy, low_pass, relative_rmse, smoothed_surface

    fa = low_pass(a["force"][:, 0], a["row_dt"], 0.1)
    fr = low_pass(ref["force"][:, 0], ref["row_dt"], 0.1)
    mean_ref = float(ref["force"][:, 0].mean())

    def surface(pos: np.ndarray) -> np.ndarray:
        return smoothed_surface(pos, bed.radii, bed.length, bed.width, sigma)

    return {
        "force_lp_rel_rmse": relative_rmse(fa, fr),
        "force_mean_rel_err": abs(float(a["force"][:, 0].mean()) - mean_ref) / abs(mean_ref),
        "surface_accuracy": height_accuracy(
            surface(a["positions"]), surface(ref["positions"]), surface(bed.positions)
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="results", help="a workflow's results folder")
    parser.add_argument("--configfile", default="config/config.yaml")
    parser.add_argument(
        "--points", nargs="*", help="scenario:speed:depth (default: the held-out points)"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--jitter", type=float, default=1e-6, help="twin's jitter, m")
    parser.add_argument("--seed", type=int, default=1, help="twin's jitter seed")
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args()

    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory
    from dozerlab.sweep import SweepPoint, bed_path, by_role, sweep_points, trajectory_path

    threads = set_threads(args.threads)
    config = load_config(args.configfile)
    if args.points:
        points = [
            SweepPoint(s, float(v), float(d), "interpolation")
            for s, v, d in (p.split(":") for p in args.points)
        ]
    else:
        every = sweep_points(config)
        points = by_role(every, "interpolation") + by_role(every, "extrapolation")
    full_cfg = copy.deepcopy(config)
    full_cfg["solver"]["active_zone"]["enabled"] = False
    zone_cfg = copy.deepcopy(config)
    zone_cfg["solver"]["active_zone"]["enabled"] = True
    zone = zone_cfg["solver"]["active_zone"]
    print(
        f"threads {threads}; zone margin {zone['margin']} m, rest {zone['rest_speed']} m/s "
        f"for {zone['rest_time']} s; twin jitter {args.jitter} m (seed {args.seed})"
    )
    print(
        f"{'point':<24} {'full s/s':>8} {'zone s/s':>8} {'speed-up':>8} {'awake':>6} "
        f"{'F_lp twin':>9} {'F_lp zone':>9} {'mean twin':>9} {'mean zone':>9} "
        f"{'surf twin':>9} {'surf zone':>9}  ok"
    )
    rows = []
    for point in points:
        bed = Bed.load(bed_path(args.results, point.scenario))
        traj = Trajectory.load_csv(trajectory_path(args.results, point))
        sim_s = traj.steps * traj.dt
        sigma = 2.0 * float(np.mean(bed.radii))
        with tempfile.TemporaryDirectory() as tmp:
            full = run(bed, traj, full_cfg, Path(tmp), "full")
            zoned = run(bed, traj, zone_cfg, Path(tmp), "zone")
            twin = run(bed.jittered(args.jitter, args.seed), traj, full_cfg, Path(tmp), "twin")
        t, z = agreement(twin, full, bed, sigma), agreement(zoned, full, bed, sigma)
        ok = (
            z["force_lp_rel_rmse"] <= t["force_lp_rel_rmse"]
            and z["force_mean_rel_err"] <= t["force_mean_rel_err"]
            and z["surface_accuracy"] >= t["surface_accuracy"]
        )
        row = {
            "point": f"{point.scenario} {point.speed}/{point.depth}",
            "full_s_per_s": full["loop_s"] / sim_s,
            "twin_s_per_s": twin["loop_s"] / sim_s,
            "zone_s_per_s": zoned["loop_s"] / sim_s,
            "speedup": full["loop_s"] / zoned["loop_s"],
            "active_fraction": zoned["active_fraction"],
            "twin": t,
            "zone": z,
            "ok": ok,
        }
        rows.append(row)
        print(
            f"{row['point']:<24} {row['full_s_per_s']:8.2f} {row['zone_s_per_s']:8.2f} "
            f"{row['speedup']:7.2f}x {row['active_fraction']:6.1%} "
            f"{t['force_lp_rel_rmse']:9.1%} {z['force_lp_rel_rmse']:9.1%} "
            f"{t['force_mean_rel_err']:9.1%} {z['force_mean_rel_err']:9.1%} "
            f"{t['surface_accuracy']:9.1%} {z['surface_accuracy']:9.1%}  {'yes' if ok else 'NO'}",
            flush=True,
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
