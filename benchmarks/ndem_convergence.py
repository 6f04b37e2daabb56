"""Solver convergence on a real bed mid-push: residual and blade force against a reference.

    python benchmarks/ndem_convergence.py --bed results/beds/hill.npz \
        --trajectory results/trajectories/hill/speed~1.0_depth~0.06.csv --config config/config.yaml

Drives the workflow's simulation (the config's solver settings) to ``--at`` of the trajectory,
then solves that one step again from the same state: with PGS for ``--reference`` iterations
(ω = 1; the reference blade force), and with each method for a list of iteration counts and of
tolerances. Prints, per method side by side, the RMS normal-row residual (m/s), the blade
force's relative error against the reference and the sweeps and seconds the step took. Not a
test: the seconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time

import numpy as np
from tqdm import tqdm


def solve_once(world, blade: int, method: str, iterations: int, tolerance: float):  # type: ignore[no-untyped-def]
    """One step of a copy of ``world``: (stats, blade force (3,) N, seconds).

    ``method`` is ``pgs``, ``nncg`` or either with ``@OMEGA`` (a relaxation factor)."""
    w = copy.deepcopy(world)
    name, _, omega = method.partition("@")
    w.method, w.iterations, w.tolerance = name, iterations, tolerance
    w.relaxation = float(omega or 1.0)
    t0 = time.perf_counter()
    stats = w.step()
    return stats, w.force_on(blade), time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bed", required=True)
    ap.add_argument("--trajectory", required=True)
    ap.add_argument("--config", required=True, help="the workflow's config (YAML or JSON)")
    ap.add_argument("--at", type=float, default=0.5, help="fraction of the trajectory to drive")
    ap.add_argument("--reference", type=int, default=1000, help="PGS iterations of the reference")
    ap.add_argument("--iterations", type=int, nargs="+", default=[10, 25, 50, 100, 200, 400])
    ap.add_argument("--tolerances", type=float, nargs="+", default=[1e-3, 3e-4, 1e-4, 3e-5])
    ap.add_argument(
        "--methods",
        nargs="+",
        default=["pgs", "pgs@1.5", "nncg"],
        help="solvers side by side: pgs, nncg, or either @OMEGA for a relaxation factor",
    )
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)

    from dozerlab.runtime import set_threads

    threads = set_threads(args.threads)
    from dozerlab.config import load_config
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.blade import add_blade
    from dozerlab.scenarios.build import make_world
    from dozerlab.scenarios.trajectory import Trajectory

    config = load_config(args.config)
    bed, traj = Bed.load(args.bed), Trajectory.load_csv(args.trajectory)
    world, _ = make_world(bed, config)
    blade = add_blade(world, traj.position[0], config)
    steps = int(args.at * traj.steps)
    for i in tqdm(range(steps), desc="driving", file=sys.stderr):
        world.set_velocity(blade, traj.velocity[i])
        world.step()
    world.set_velocity(blade, traj.velocity[steps])

    ref, f_ref, t_ref = solve_once(world, blade, "pgs@1.0", args.reference, 0.0)
    print(
        f"bed {args.bed}: {world.n_spheres} spheres, step {steps} of {traj.steps}, {threads} threads"
    )
    print(
        f"reference: PGS {args.reference} iterations, {ref.contacts} contacts "
        f"(+{ref.speculative} speculative), residual {ref.residual:.2e} m/s, "
        f"blade force {np.round(f_ref, 1).tolist()} N, {t_ref:.2f} s"
    )

    def row(label: str, runs: list) -> None:  # type: ignore[type-arg]
        cells = []
        for stats, f, sec in runs:
            err = np.linalg.norm(f - f_ref) / np.linalg.norm(f_ref)
            cells.append(f"{stats.iterations:5d} {stats.residual:9.2e} {err:9.2e} {sec:6.2f}")
        print(f"{label:>16} | " + " | ".join(cells))

    head = " | ".join(f"{m:^31}" for m in args.methods)
    cols = " | ".join(
        f"{'sweeps':>5} {'residual':>9} {'force err':>9} {'s':>6}" for _ in args.methods
    )
    print(f"\n{'iterations':>16} | {head}\n{'':>16} | {cols}")
    for it in args.iterations:
        row(str(it), [solve_once(world, blade, m, it, 0.0) for m in args.methods])
    print(f"\n{'tolerance (m/s)':>16} | {head}\n{'':>16} | {cols}")
    for tol in args.tolerances:
        row(f"{tol:g}", [solve_once(world, blade, m, args.reference, tol) for m in args.methods])


if __name__ == "__main__":
    main()
