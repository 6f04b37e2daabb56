"""How cost grows with the terrain: NDEM (full solve and active zone) and the reduced loop on
beds of 1x, 2x and 4x the default area, same blade and path, in one run.

    python benchmarks/reduce_scaling.py --results results [--points hill:0.875:0.045 ...] \\
        [--config config/config.yaml] [--steps 60] [--tiles 1 2 4] [--threads 1] \\
        [--dynamics replay ridge] [--plot docs/images/reduce-scaling.png]

The larger beds are the point's settled bed repeated across its width (copies side by side, each
shifted by the bed's width, so the terrain under the blade's path is the same); a seam is not
settled (a wall's contacts become the next copy's grains, and NDEM's first step sets the grains
along it moving; the reduced loop too, when its warm-up is NDEM's), so the larger beds overstate
how NDEM grows. The blade runs the first ``--steps`` steps of the point's trajectory on each. Per bed,
side by side on one machine and thread count: the full NDEM solve, NDEM with
``solver.active_zone.enabled``, and the reduced loop of each ``--dynamics`` model: ``replay``
(the full solve's own fields: the loop's cost with perfect fields, no inference) and the
workflow's trained evolution models under ``--results`` (``results/dynamics/{model}``, with the
force model rule ``reduce`` gives it: what a user runs instead of NDEM). Printed per bed and
loop: grains, wall time per simulated second of each (the reduced loop's with and without its
warm-up rows: NDEM's steps when the blade reaches a grain in them, else the bed sampled as it
lies) and the speed-ups over both NDEMs; the figure plots the wall time per simulated second
against the bed's area (the first point's, where ``--tiles`` gives more than one size).
``--points held-out`` runs the config's held-out points (interpolation, extrapolation and
transfer) one after the other, and ends with a table of each point's speed-ups: the loops beside
both NDEMs on the points the workflow compares. Not a test: the times depend on the machine and
its load.
"""

from __future__ import annotations

import argparse
import copy
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from dozerlab.sweep import SweepPoint


def tiled(bed: Any, tiles: int) -> Any:
    """``bed`` repeated ``tiles`` times across its width, centred on y = 0 (a Bed)."""
    from dozerlab.scenarios.bed import Bed

    shifts = (np.arange(tiles) - (tiles - 1) / 2.0) * bed.width
    return Bed(
        scenario=bed.scenario,
        length=bed.length,
        width=bed.width * tiles,
        positions=np.concatenate([bed.positions + np.array([0.0, s, 0.0]) for s in shifts]),
        radii=np.tile(bed.radii, tiles),
        masses=np.tile(bed.masses, tiles),
        velocities=np.tile(bed.velocities, (tiles, 1)),
        angular_velocities=np.tile(bed.angular_velocities, (tiles, 1)),
        material=bed.material,
        seed=bed.seed,
        info={**bed.info, "tiles": tiles},
    )


def ndem(
    bed: Path, traj: Path, config: dict[str, Any], store: Path, labels: dict[str, Any]
) -> float:
    """One NDEM simulate loop of the bed and trajectory files into ``store``; its loop wall
    time, s."""
    from dozerlab.fields.jobs import simulate

    return float(simulate(bed, traj, config, store, **labels)["wall_time_s"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results", help="a workflow's results folder")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument(
        "--points",
        nargs="+",
        default=["hill:0.875:0.045"],
        help="scenario:speed:depth of each point, or held-out (the config's held-out points)",
    )
    ap.add_argument("--steps", type=int, default=60, help="solver steps of the path to run")
    ap.add_argument("--tiles", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--dynamics",
        nargs="+",
        default=["replay", "ridge"],
        help="the reduced loops to time: replay and/or trained evolution models under --results",
    )
    ap.add_argument("--plot", default="docs/images/reduce-scaling.png")
    args = ap.parse_args()
    os.environ["DOZERLAB_MLFLOW"] = "0"

    from dozerlab import sweep as P
    from dozerlab.config import load_config
    from dozerlab.reduce.models import ForcePredictor, load_field_model
    from dozerlab.runtime import set_threads
    from dozerlab.scenarios.bed import Bed

    args.threads = set_threads(args.threads)
    config = load_config(args.config)
    if args.points == ["held-out"]:
        every = P.sweep_points(config)
        points = [p for role in P.HELD_OUT_ROLES for p in P.by_role(every, role)]
    else:
        points = [
            P.SweepPoint(s, float(v), float(d))
            for s, v, d in (spec.split(":") for spec in args.points)
        ]
    res = Path(args.results)
    grid = tuple(config["sampling"]["bins"])
    forces = {
        name: ForcePredictor(P.reduce_force_model_path(res, config["reduced"], name))
        for name in args.dynamics
    }
    learned = {
        name: load_field_model(P.dynamics_model_path(res, name), grid)
        for name in args.dynamics
        if name != "replay"
    }
    runs = {point: point_rows(point, res, config, args, forces, learned) for point in points}
    if len(points) > 1:
        print("\nspeed-up of each loop (with its warm-up) over NDEM's full solve / its zone:")
        for point, rows in runs.items():
            for row in rows:
                print(
                    f"{point.scenario:>7} {point.name:>24} {row['tiles']}x: "
                    + ", ".join(
                        f"{name} {row['full'] / row[name]:.1f}x / {row['zone'] / row[name]:.1f}x"
                        for name in args.dynamics
                    )
                )
    first, rows = next(iter(runs.items()))
    if len(rows) > 1:
        bed = Bed.load(P.bed_path(res, first.scenario))
        plot(
            rows,
            args.dynamics,
            bed.length * bed.width,
            Path(args.plot),
            f"{first.scenario} {first.speed:g} m/s, {first.depth:g} m deep: "
            f"{rows[0]['sim_s']:.2f} s of the pass",
        )
        print(f"plot: {args.plot}")


def point_rows(
    point: SweepPoint,
    res: Path,
    config: dict[str, Any],
    args: argparse.Namespace,
    forces: dict[str, Any],
    learned: dict[str, Any],
) -> list[dict[str, Any]]:
    """One point's beds (``args.tiles``) timed under both NDEMs and each reduced loop: a row
    per bed, wall times per simulated second."""
    from dozerlab import sweep as P
    from dozerlab.reduce.models import load_field_model
    from dozerlab.reduce.run import reduce_run
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory

    full_cfg = copy.deepcopy(config)
    full_cfg["solver"]["active_zone"]["enabled"] = False
    zone_cfg = copy.deepcopy(config)
    zone_cfg["solver"]["active_zone"]["enabled"] = True
    bed = Bed.load(P.bed_path(res, point.scenario))
    whole = Trajectory.load_csv(P.trajectory_path(res, point))
    k = min(args.steps, whole.steps)
    traj = Trajectory(
        whole.time[: k + 1],
        whole.position[: k + 1],
        whole.velocity[:k],
        whole.speed,
        whole.depth,
        whole.scenario,
        whole.goal_height,
        whole.dt,
    )
    sim_s = k * traj.dt
    labels = {"scenario": point.scenario, "speed": point.speed, "depth": point.depth}
    grid = tuple(config["sampling"]["bins"])
    print(
        f"\n{point.scenario} {point.name}: first {k} steps ({sim_s:.2f} s simulated), "
        f"{args.threads} thread(s); wall time per simulated second"
    )
    print(
        f"{'area':>5} {'grains':>7} {'NDEM full':>9} {'NDEM zone':>9} {'loop':>8} {'reduced':>8} "
        f"{'red. steps':>10} {'full/red':>8} {'zone/red':>8}  reduced step: ms by phase"
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        traj_path = t / "trajectory.csv"
        traj.save_csv(traj_path)
        for n in args.tiles:
            b = tiled(bed, n)
            bed_path = t / f"bed{n}.npz"
            b.save(bed_path)
            store = t / f"full{n}.zarr"
            full = ndem(bed_path, traj_path, full_cfg, store, labels)
            zone = ndem(bed_path, traj_path, zone_cfg, t / f"zone{n}.zarr", labels)
            row: dict[str, Any] = {
                "tiles": n,
                "grains": b.count,
                "sim_s": sim_s,
                "full": full / sim_s,
                "zone": zone / sim_s,
            }
            for name in args.dynamics:
                fm = load_field_model("replay", grid, store) if name == "replay" else learned[name]
                r = reduce_run(
                    bed_path,
                    traj_path,
                    full_cfg,
                    fm,
                    forces[name],
                    t / f"{name}{n}.zarr",
                    t / f"{name}{n}.npz",
                    **labels,
                )
                steps_s = r["wall_time_s"] - r["warmup_s"]
                every = int(config["sampling"]["every"])
                row[name] = r["wall_time_s"] / sim_s
                # the reduced steps alone, per simulated second of them
                row[f"{name}_steps"] = steps_s / (r["reduced_rows"] * every * traj.dt)
                print(
                    f"{n:>4}x {row['grains']:>7} {row['full']:9.2f} {row['zone']:9.2f} "
                    f"{name:>8} {row[name]:8.2f} {row[f'{name}_steps']:10.2f} "
                    f"{row['full'] / row[name]:7.1f}x {row['zone'] / row[name]:7.1f}x  "
                    + ", ".join(f"{k[3:]} {v:.1f}" for k, v in r.items() if k.startswith("ms_"))
                    + f"; grains moved a step {r['active_grains_mean']:.0f}",
                    flush=True,
                )
            rows.append(row)
    return rows


def plot(rows: list[dict[str, Any]], loops: list[str], area: float, out: Path, title: str) -> None:
    """Wall time per simulated second (s/s) against the bed's area (m²), one line per solver
    and reduced loop (``loops``: the dynamics models), its steps alone dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [area * r["tiles"] for r in rows]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for key, label in (("full", "NDEM, full solve"), ("zone", "NDEM, active zone")):
        ax.plot(x, [r[key] for r in rows], "o-", label=label)
    for name in loops:
        (line,) = ax.plot(x, [r[name] for r in rows], "s-", label=f"reduced loop ({name})")
        ax.plot(
            x,
            [r[f"{name}_steps"] for r in rows],
            "s--",
            color=line.get_color(),
            alpha=0.6,
            label=f"reduced loop ({name}), its steps only",
        )
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{a:g}" for a in x])
    ax.set_xlabel("bed area (m²)")
    ax.set_ylabel("wall time per simulated second (s/s)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
