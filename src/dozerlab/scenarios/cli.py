"""``dozerlab bed`` and ``dozerlab trajectory`` — build a scenario's bed, plan a blade path."""

from __future__ import annotations

import argparse

from dozerlab.cliargs import add_command, add_config, add_point, add_threads, configure


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "bed",
        "build and settle a scenario's particle bed",
        "python -m dozerlab bed --scenario hill --config config/quick.yaml \\\n"
        "      --out results/beds/hill.npz --plot results/beds/hill.png",
    )
    p.add_argument(
        "--scenario",
        required=True,
        help="a preset (hill, step, trench) or a scenario the config defines",
    )
    add_config(p)
    p.add_argument("--out", required=True, help="bed file to write (.npz)")
    p.add_argument("--plot", default=None, help="also write a PNG of the bed and its settle log")
    add_threads(p)
    p.add_argument(
        "--no-progress", dest="progress", action="store_false", help="hide the progress bar"
    )
    p.set_defaults(func=_bed)

    p = add_command(
        sub,
        "trajectory",
        "plan a blade path over a bed at a sweep point's speed and depth",
        "python -m dozerlab trajectory --bed results/beds/hill.npz --speed 1.0 --depth 0.04 \\\n"
        "      --config config/quick.yaml --out results/trajectories/hill/speed~1.0_depth~0.04.csv",
    )
    p.add_argument("--bed", required=True, help="bed file written by 'dozerlab bed'")
    add_point(
        p,
        "blade speed along the path in m/s (0.01 to 20, the bounds of sweep.speeds)",
        "cut depth in m (0.001 to 10, the bounds of sweep.depths, and less than the bed's height)",
        required=True,
    )
    add_config(p)
    p.add_argument("--out", required=True, help="CSV to write: step,time,x,y,z,vx,vy,vz")
    p.add_argument(
        "--plot", default=None, help="also write a PNG of the height field, path and velocities"
    )
    p.set_defaults(func=_trajectory)


def _bed(args: argparse.Namespace) -> int:
    config = configure(args)
    from dozerlab.scenarios.jobs import bed_job

    bed_job(args.scenario, config, args.out, plot=args.plot, progress=args.progress)
    return 0


def _trajectory(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.scenarios.jobs import trajectory_job

    trajectory_job(
        args.bed, args.speed, args.depth, load_config(args.config), args.out, plot=args.plot
    )
    return 0
