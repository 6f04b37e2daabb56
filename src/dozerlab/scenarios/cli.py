"""``dozerlab bed`` and ``dozerlab trajectory`` — build a scenario's bed, plan a blade path."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bed", help="build and settle a scenario's particle bed")
    p.add_argument("--scenario", required=True, help="hill or step")
    p.add_argument(
        "--config", default=None, help="YAML file or inline JSON (default: all defaults)"
    )
    p.add_argument("--out", required=True, help="bed file to write (.npz)")
    p.add_argument("--plot", default=None, help="also write a PNG of the bed and its settle log")
    p.add_argument("--threads", type=int, default=1, help="numba threads (default 1)")
    p.add_argument(
        "--no-progress", dest="progress", action="store_false", help="hide the progress bar"
    )
    p.set_defaults(func=_bed)

    p = sub.add_parser("trajectory", help="plan a blade path over a bed (SPEC §4)")
    p.add_argument("--bed", required=True, help="bed file written by 'dozerlab bed'")
    p.add_argument(
        "--speed", type=float, required=True, help="blade speed along the path in m/s (> 0)"
    )
    p.add_argument(
        "--depth",
        type=float,
        required=True,
        help="cut depth in m (> 0, less than the bed's height)",
    )
    p.add_argument(
        "--config", default=None, help="YAML file or inline JSON (default: all defaults)"
    )
    p.add_argument("--out", required=True, help="CSV to write: step,time,x,y,z,vx,vy,vz")
    p.add_argument(
        "--plot", default=None, help="also write a PNG of the height field, path and velocities"
    )
    p.set_defaults(func=_trajectory)


def _bed(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads
    from dozerlab.scenarios.bed import SCENARIOS

    if args.scenario not in SCENARIOS:
        raise ValueError(f"--scenario must be one of {list(SCENARIOS)}, got {args.scenario!r}")
    config = load_config(args.config)
    set_threads(args.threads)

    from dozerlab.runtime import FIGURE, check_output
    from dozerlab.scenarios.bed import BED_FILE
    from dozerlab.scenarios.build import build_bed

    check_output(args.out, BED_FILE)  # before the settling, not after it
    if args.plot:
        check_output(args.plot, FIGURE)
    from dozerlab.scenarios.plots import plot_bed
    from dozerlab.tracking import tracked_run

    params = {k: config[k] for k in ("bed", "material", "solver", "seed")}
    params["scenario"] = config["scenarios"][args.scenario]
    with tracked_run(
        f"bed {args.scenario}", rule="bed", tags={"scenario": args.scenario}, params=params
    ) as run:
        bed = build_bed(args.scenario, config, progress=args.progress)
        bed.save(args.out)
        if args.plot:
            plot_bed(bed, args.plot)
        if run is not None:
            import mlflow

            mlflow.log_metrics(
                {
                    "particle_count": bed.count,
                    "settle_time": bed.info["time"],
                    "kinetic_energy_per_particle": bed.kinetic_energy_per_particle(),
                    "wall_time": bed.info["wall_time"],
                    "steps": bed.info["steps"],
                }
            )
            if args.plot:
                mlflow.log_artifact(args.plot)
    return 0


def _trajectory(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.runtime import FIGURE, check_output
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import TRAJECTORY_FILE, plan_trajectory, plot_trajectory

    config = load_config(args.config)
    check_output(args.out, TRAJECTORY_FILE)
    if args.plot:
        check_output(args.plot, FIGURE)
    traj = plan_trajectory(Bed.load(args.bed), args.speed, args.depth, config)
    traj.save_csv(args.out)
    if args.plot:
        plot_trajectory(traj, args.plot)
    return 0
