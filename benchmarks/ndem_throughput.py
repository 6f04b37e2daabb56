"""NDEM throughput: settle a bed of spheres, then time steps and print contact-iterations/s.

    python benchmarks/ndem_throughput.py --particles 20000 --threads 2 --steps 20
    python benchmarks/ndem_throughput.py --particles 15000 --radius 0.025 --threads 1 \
        --config config/config.yaml      # the workflow's solver settings and one thread per job

A contact-iteration is one sweep's update of one contact (normal, friction and rolling rows). The
count includes the speculative near contacts the solver also updates and uses the sweeps each
step actually ran. Not a test: the figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from tqdm import tqdm


def build_bed(world, n: int, radius: float, seed: int) -> None:
    """n spheres on a jittered lattice in a walled 4 m × 2 m box, ground at z = 0."""
    spacing = 2.1 * radius
    nx, ny = int(4.0 / spacing) - 1, int(2.0 / spacing) - 1
    nz = int(np.ceil(n / (nx * ny)))
    idx = np.stack(np.unravel_index(np.arange(n), (nz, nx, ny)), axis=1)[:, [1, 2, 0]]
    rng = np.random.default_rng(seed)
    pos = (idx + 0.5) * spacing + rng.uniform(-0.04, 0.04, (n, 3)) * radius
    pos[idx[:, 2] % 2 == 1, :2] += 0.5 * spacing  # odd layers fall into the pockets below
    pos += [0.0, -1.0, 0.0]
    world.add_plane((0, 0, 0), (0, 0, 1))
    world.add_plane((0, 0, 0), (1, 0, 0))
    world.add_plane(((nx + 0.5) * spacing, 0, 0), (-1, 0, 0))
    world.add_plane((0, -1.0, 0), (0, 1, 0))
    world.add_plane((0, -1.0 + (ny + 0.5) * spacing, 0), (0, -1, 0))
    world.add_spheres(pos, radius=radius * rng.uniform(0.9, 1.0, n))


def parallel_ceiling(threads: int) -> float:
    """Speed-up of a compute-bound, perfectly parallel numba loop from 1 to ``threads`` threads.

    The most any solver can gain on this machine: virtual cores that share physical ones fall
    short of a linear gain even with no memory traffic or synchronisation.
    """
    import numba

    @numba.njit(parallel=True)
    def work(n: int) -> float:
        total = 0.0
        for i in numba.prange(n):
            x = 0.0
            for j in range(200):
                x += np.sin(i * 1e-3 + j)
            total += x
        return total

    work(1000)
    seconds = []
    for t in (1, threads):
        numba.set_num_threads(t)
        t0 = time.perf_counter()
        work(400_000)
        seconds.append(time.perf_counter() - t0)
    return seconds[0] / seconds[1]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=20000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=20, help="timed steps")
    ap.add_argument("--settle", type=int, default=100, help="settling steps before timing")
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--method", default=None, help="pgs or nncg (default: the schema's)")
    ap.add_argument("--relaxation", type=float, default=None, help="ω (default: the schema's)")
    ap.add_argument("--tolerance", type=float, default=0.0, help="residual stop in m/s")
    ap.add_argument(
        "--config",
        default=None,
        help="take iterations, method, relaxation and tolerance from this config's solver section",
    )
    ap.add_argument("--radius", type=float, default=0.05)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    from dozerlab.runtime import set_threads

    threads = set_threads(args.threads)
    from dozerlab.ndem import World

    solver = {"iterations": args.iterations, "tolerance": args.tolerance}
    solver |= {k: getattr(args, k) for k in ("method", "relaxation") if getattr(args, k)}
    if args.config:
        from dozerlab.config import load_config

        cfg = load_config(args.config)["solver"]
        solver = {k: cfg[k] for k in ("iterations", "method", "relaxation", "tolerance")}
    world = World(dt=0.01, **solver)
    build_bed(world, args.particles, args.radius, args.seed)
    t0 = time.perf_counter()
    world.step()
    print(
        f"first step (includes compiling or loading kernels): {time.perf_counter() - t0:.1f} s",
        file=sys.stderr,
    )
    for _ in tqdm(range(args.settle), desc="settling", file=sys.stderr):
        world.step()
    rows = row_sweeps = sweeps = 0
    t0 = time.perf_counter()
    for _ in tqdm(range(args.steps), desc="timing", file=sys.stderr):
        stats = world.step()
        rows += stats.contacts + stats.speculative
        row_sweeps += (stats.contacts + stats.speculative) * stats.iterations
        sweeps += stats.iterations
    elapsed = time.perf_counter() - t0
    print(f"particles            {world.n_spheres}")
    print(f"threads              {threads}")
    print(
        f"solver               {world.method}, ω = {world.relaxation}, at most "
        f"{world.iterations} sweeps, tolerance {world.tolerance} m/s"
    )
    print(f"sweeps per step      {sweeps / args.steps:.1f}")
    print(f"contacts per step    {rows / args.steps:.0f} (touching now: {stats.contacts})")
    print(f"steps per second     {args.steps / elapsed:.3f}")
    print(f"contact-iterations/s {row_sweeps / elapsed:.3e}")
    print(f"residual (m/s)       {stats.residual:.3e}")
    print(f"max overlap          {stats.max_overlap_fraction:.3f} of the radius")
    if threads > 1:
        print(
            f"machine ceiling      {parallel_ceiling(threads):.2f}x from 1 to {threads} threads "
            "(a perfectly parallel compute loop)"
        )


if __name__ == "__main__":
    main()
