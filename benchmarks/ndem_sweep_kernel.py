"""The PGS sweep kernel alone, on one step's contact system of a default bed mid-push.

    NUMBA_NUM_THREADS=1 python benchmarks/ndem_sweep_kernel.py \\
        --bed /work/verify/H/results/beds/hill.npz \\
        --trajectory "/work/verify/H/results/trajectories/hill/speed~0.875_depth~0.045.csv" \\
        --config config/config.yaml --steps 120 --baseline main --repeats 5

Drives the blade along the trajectory from the bed (as ``benchmarks/ndem_solver_run.py`` does)
with the baseline kernel for ``--steps`` steps, then snapshots the next step's assembled contact
system just before :func:`dozerlab.ndem.solver.solve` (``--snapshot`` keeps it in a ``.npz`` for
later runs) and times ``solve`` on fresh copies of it, ``--repeats`` times each, side by side in
one process: the baseline kernel (``solver.py`` as committed at the git ref ``--baseline``,
loaded beside the working tree's) and the working tree's. Prints contact-iterations/s (best and
median of the repeats) and the largest difference of the multipliers and velocities against the
baseline. ``--spin`` adds the working tree's kernel with the spinning row on (its difference
from the baseline is then the row's effect, not round-off).
Not a test: the seconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np

ARRAYS = ("ci", "cj", "cd", "lam", "v", "w", "invm", "invI", "start")
SCALARS = ("n_slabs", "iterations", "warm", "method", "tolerance", "omega")
# the spinning resistance μ_s, passed only when nonzero: a baseline from before it had no such
# argument, and with 0 both kernels solve the same rows
SPIN = "spin"


def snapshot(bed: str, trajectory: str, config_path: str, steps: int, solve) -> dict:
    """Drive ``steps`` steps with ``solve`` as the stepper's solver (so the snapshot does not
    depend on the kernel under test), then return the arguments of the next step's call."""
    from dozerlab.config import load_config
    from dozerlab.ndem import solver
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.blade import add_blade
    from dozerlab.scenarios.build import make_world
    from dozerlab.scenarios.trajectory import Trajectory

    config = load_config(config_path)
    traj = Trajectory.load_csv(trajectory)
    if not 0 <= steps < traj.steps:
        raise SystemExit(f"--steps must be in [0, {traj.steps - 1}], got {steps}")
    world, _ = make_world(Bed.load(bed), config)
    blade = add_blade(world, traj.position[0], config)
    captured: dict = {}

    def capture(*args):
        if world.state.step_count == steps:
            captured.update({k: np.copy(a) for k, a in zip(ARRAYS, args[:9], strict=True)})
            captured.update(dict(zip(SCALARS, args[9:15], strict=True)))
            captured[SPIN] = float(args[15]) if len(args) > 15 else 0.0
        spin = args[15:]  # (μ_s,) from a stepper that passes it
        return solve(*args[:15], *(spin if spin and spin[0] else ()))

    working = solver.solve
    solver.solve = capture  # the stepper calls solver.solve through the module
    try:
        for i in range(steps + 1):
            world.set_velocity(blade, traj.velocity[i])
            world.step()
    finally:
        solver.solve = working
    captured["driven"] = steps
    return captured


def load_baseline(ref: str) -> ModuleType:
    """``dozerlab/ndem/solver.py`` as committed at git ``ref``, imported as its own module."""
    text = subprocess.run(
        ["git", "show", f"{ref}:src/dozerlab/ndem/solver.py"],
        check=True,
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parent,
    ).stdout
    folder = Path(tempfile.mkdtemp(prefix="solver_baseline_"))
    path = folder / "solver_baseline.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("solver_baseline", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(solve, snap: dict) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """One ``solve`` on copies of the snapshot; returns seconds and the lam, v, w it left."""
    lam, v, w = np.copy(snap["lam"]), np.copy(snap["v"]), np.copy(snap["w"])
    args = [snap[k] for k in ARRAYS]
    args[3:6] = lam, v, w
    t0 = time.perf_counter()
    solve(*args, *(snap[k] for k in SCALARS), *([snap[SPIN]] if snap[SPIN] else []))
    return time.perf_counter() - t0, lam, v, w


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bed", required=True)
    ap.add_argument("--trajectory", required=True)
    ap.add_argument("--config", required=True)
    ap.add_argument("--steps", type=int, default=120, help="steps driven before the snapshot")
    ap.add_argument("--baseline", default="main", help="git ref of the baseline solver.py")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--snapshot", help=".npz that keeps the snapshot (read when it exists)")
    ap.add_argument(
        "--spin",
        type=float,
        default=0.0,
        help="also time the working tree's kernel with this spinning resistance μ_s",
    )
    args = ap.parse_args(argv)

    import numba

    from dozerlab.ndem import solver

    baseline = load_baseline(args.baseline).solve
    if args.snapshot and Path(args.snapshot).exists():
        with np.load(args.snapshot, allow_pickle=False) as f:
            snap = {k: f[k] for k in ARRAYS} | {k: f[k].item() for k in (*SCALARS, "driven")}
            snap[SPIN] = f[SPIN].item() if SPIN in f else 0.0
    else:
        snap = snapshot(args.bed, args.trajectory, args.config, args.steps, baseline)
        if args.snapshot:
            np.savez(args.snapshot, **snap)
    nc, n = snap["ci"].shape[0], snap["v"].shape[0]
    print(
        f"snapshot after {snap['driven']} steps: {nc} contacts, {n} spheres, "
        f"{snap['n_slabs']} slabs,"
        f" {snap['iterations']} sweeps, omega {snap['omega']}, method {snap['method']},"
        f" spinning resistance {snap[SPIN]},"
        f" {numba.get_num_threads()} numba thread(s)"
    )
    kernels = {f"baseline ({args.baseline})": (baseline, snap)}
    kernels["working tree"] = (solver.solve, snap)
    if args.spin:
        kernels[f"working tree, μ_s {args.spin}"] = (solver.solve, snap | {SPIN: args.spin})
    for solve, system in kernels.values():
        run(solve, system)  # compile or load from the cache
    times: dict[str, list[float]] = {name: [] for name in kernels}
    out = {}
    for _ in range(args.repeats):  # interleaved, so drifting load hits both alike
        for name, (solve, system) in kernels.items():
            seconds, *out[name] = run(solve, system)
            times[name].append(seconds)
    ref = out[next(iter(kernels))]
    base = statistics.median(times[next(iter(kernels))])
    work = nc * snap["iterations"]
    for name in kernels:
        best, median = min(times[name]), statistics.median(times[name])
        diff = [float(np.abs(a - b).max(initial=0.0)) for a, b in zip(out[name], ref, strict=True)]
        print(
            f"{name:24s} {1e3 * median:7.1f} ms median ({1e3 * best:6.1f} best), "
            f"{work / median:.3g} contact-iterations/s, {base / median:.2f}x; max |diff| "
            f"lam {diff[0]:.2g} N·s, v {diff[1]:.2g} m/s, w {diff[2]:.2g} rad/s"
        )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
