"""A whole simulation run per solver setting: stepping time, largest overlap, blade force.

    python benchmarks/ndem_solver_run.py --bed results/beds/hill.npz \\
        --trajectory results/trajectories/hill/speed~1.5_depth~0.08.csv --config config/quick.yaml \\
        --solvers pgs:1.0:100 pgs:1.5:60 pgs:1.0:200 pgs:1.5:100

Each solver is METHOD:RELAXATION:ITERATIONS[:RELINEARIZE[:TOLERANCE[:ABOVE]]]
(``solver.relinearize``, ``solver.tolerance`` and ``solver.relinearize_above`` the schema's
defaults unless given; ABOVE 0 runs the rounds in every step). The run drives the blade along the
trajectory from the bed as the ``simulate`` job does (without sampling) and prints, side by
side in one process, the seconds spent stepping, the largest overlap over the smaller radius
(how soft the bed got: the divergence guard is ``solver.max_overlap``), the mean sweeps and
the blade's mean push force. ``--perturb`` repeats each run with the bed's initial velocities
scaled by 1 + EPS: a round-off-sized EPS (1e-13) shows how far a run spreads on its own, the
yardstick for a change that alters only round-off. Not a test: the seconds depend on the
machine and its load.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bed", required=True)
    ap.add_argument("--trajectory", required=True)
    ap.add_argument("--config", required=True)
    ap.add_argument(
        "--solvers", nargs="+", required=True, help="METHOD:RELAXATION:ITERATIONS[:RELINEARIZE]"
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--perturb", type=float, nargs="+", default=[0.0], metavar="EPS")
    args = ap.parse_args(argv)

    from dozerlab.runtime import set_threads

    set_threads(args.threads)
    from dozerlab.config import load_config
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.blade import add_blade
    from dozerlab.scenarios.build import make_world
    from dozerlab.scenarios.trajectory import Trajectory

    config = load_config(args.config)
    traj, bed = Trajectory.load_csv(args.trajectory), Bed.load(args.bed)
    for spec, eps in ((s, e) for s in args.solvers for e in args.perturb):
        method, omega, iterations, *more = spec.split(":")
        solver = {"method": method, "relaxation": float(omega), "iterations": int(iterations)}
        if more:
            solver["relinearize"] = int(more[0])
        if len(more) > 1:
            solver["tolerance"] = float(more[1])
        if len(more) > 2:
            solver["relinearize_above"] = float(more[2])
        world, _ = make_world(bed, {**config, "solver": {**config["solver"], **solver}})
        world.state.v *= 1.0 + eps
        blade = add_blade(world, traj.position[0], config)
        seconds, overlap, sweeps, fx, extra = 0.0, 0.0, 0, [], 0
        for i in range(traj.steps):
            world.set_velocity(blade, traj.velocity[i])
            t0 = time.perf_counter()
            stats = world.step()
            seconds += time.perf_counter() - t0
            overlap = max(overlap, stats.max_overlap_fraction)
            sweeps += stats.iterations
            extra += stats.iterations > int(iterations)  # a re-linearisation round ran
            fx.append(world.force_on(blade)[0])
        print(
            f"{spec:16s} eps {eps:8.1e} stepping {seconds:6.2f} s, "
            f"largest overlap {overlap:.3f} r, {sweeps / traj.steps:.0f} sweeps/step, "
            f"re-linearised in {extra} of {traj.steps} steps, "
            f"mean push {-np.mean(fx):8.1f} N"
        )


if __name__ == "__main__":
    main()
