"""Impacts at the working time step: a jittered lattice of grains dropped on the ground.

    python benchmarks/ndem_drop.py --solvers "relinearize=0" "" "relinearize_above=0"

The lattice: ``--layers`` layers of ``--grid`` (x, y) grains ``--spacing`` apart (12 × 68 × 17 =
13 872 grains 5.8 cm apart by default), radii r·(1 ± 10 %) with r = 2.5 cm, each centre
jittered by up to half the free space (spacing − largest diameter) along each axis, the lowest
layer lifted so that it reaches the ground at ``--impact`` m/s (1.5); the upper layers land on
the ones below at up to ~2 m/s. The box is the lattice plus 2.8 cm along x and 0.7 cm along y
(4 m × 1 m by default), the ground and four walls; E 1e8 Pa, μ 0.5, μ_r 0.1, density 2600
kg/m³, ``solver.dt`` 0.01 s unless a solver says otherwise.

Each solver is a comma-separated list of ``solver`` fields over the schema's defaults
(``iterations=200,relinearize=0``; ``""`` the defaults). Printed per solver, side by side in one
process: the largest overlap over the smaller radius at the start of every ``--every``-th step
(and every step above 5 %), the steps run, the largest overlap of the run, the mean sweeps per
step, the wall time of the stepping and the fastest grain's speed at the end; a
``DivergenceError`` ends that solver's run and is printed. Not a test: the seconds depend on
the machine and its load (tests/ndem/test_solver.py drops a smaller lattice).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

R = 0.025


def drop_world(
    grid: tuple[int, int],
    layers: int,
    spacing: float,
    impact: float,
    seed: int,
    solver: dict[str, object],
):  # type: ignore[no-untyped-def]
    """A World holding the jittered lattice above the ground inside its walls."""
    from dozerlab.config import load_config
    from dozerlab.ndem import World
    from dozerlab.scenarios.build import add_walls

    config = load_config({"solver": solver})
    world = World.from_config(config)
    nx, ny = grid
    length, width = nx * spacing + 0.056, ny * spacing + 0.014
    add_walls(world, length, width, float(config["material"]["wall_friction"]))
    rng = np.random.default_rng(seed)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(layers), indexing="ij")
    rmax = 1.1 * R
    lift = impact**2 / (2.0 * 9.81)
    x = np.stack(
        [
            0.028 + (i + 0.5) * spacing,
            -0.5 * width + 0.007 + (j + 0.5) * spacing,
            rmax + lift + k * spacing,
        ],
        axis=-1,
    ).reshape(-1, 3)
    jitter = 0.5 * (spacing - 2.0 * rmax)
    x += rng.uniform(-jitter, jitter, x.shape)
    world.add_spheres(x, R * (1.0 + 0.1 * rng.uniform(-1.0, 1.0, len(x))), 2600.0, 0.5, 0.1)
    return world


def _solver(spec: str) -> dict[str, object]:
    out: dict[str, object] = {}
    for item in filter(None, spec.split(",")):
        key, value = item.split("=")
        out[key] = float(value) if "." in value or "e" in value else int(value)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--solvers",
        nargs="+",
        default=["relinearize=0", "", "relinearize_above=0"],
        help="FIELD=VALUE,... per solver",
    )
    ap.add_argument("--grid", type=int, nargs=2, default=[68, 17])
    ap.add_argument("--layers", type=int, default=12)
    ap.add_argument("--spacing", type=float, default=0.058)
    ap.add_argument("--impact", type=float, default=1.5, help="m/s of the lowest layer")
    ap.add_argument("--time", type=float, default=2.0, help="simulated s")
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    from dozerlab.runtime import set_threads

    set_threads(args.threads)
    from dozerlab.ndem.stats import DivergenceError

    for spec in args.solvers:
        world = drop_world(
            tuple(args.grid), args.layers, args.spacing, args.impact, args.seed, _solver(spec)
        )
        steps = round(args.time / world.dt)
        p = world.params
        print(
            f"\n[{spec or 'defaults'}] {world.n_spheres} grains, dt {p.dt} s, {p.iterations} "
            f"sweeps at most, tolerance {p.tolerance} m/s ({p.rest_tolerance} m/s while no body moves), relinearize {p.relinearize} past "
            f"{p.relinearize_above} r"
        )
        seconds, worst, sweeps, done, line = 0.0, 0.0, 0, 0, []
        try:
            for s in range(steps):
                t0 = time.perf_counter()
                stats = world.step()
                seconds += time.perf_counter() - t0
                done += 1
                sweeps += stats.iterations
                worst = max(worst, stats.max_overlap_fraction)
                if s % args.every == 0 or stats.max_overlap_fraction > 0.05:
                    line.append(f"{s + 1}:{stats.max_overlap_fraction:.3f}")
        except DivergenceError as err:
            print(f"  DivergenceError: {err}")
        print("  largest overlap at step: " + " ".join(line))
        speed = float(np.linalg.norm(world.velocities, axis=1).max())
        print(
            f"  {done} of {steps} steps, largest overlap {worst:.4f} r, "
            f"{sweeps / max(done, 1):.0f} sweeps/step, stepping {seconds:.1f} s, "
            f"fastest grain at the end {speed:.3f} m/s"
        )


if __name__ == "__main__":
    main()
