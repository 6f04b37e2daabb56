"""Milliseconds per NDEM step in each phase of the step, on a default bed mid-push.

    NUMBA_NUM_THREADS=1 python benchmarks/ndem_step_phases.py \\
        --bed /work/verify/H/results/beds/hill.npz \\
        --trajectory /work/verify/H/results/trajectories/hill/speed~1.0_depth~0.06.csv \\
        --start 150 --steps 30 --save /tmp/phases.npz      # or --compare /tmp/phases.npz
    NUMBA_NUM_THREADS=1 python benchmarks/ndem_step_phases.py --build hill --length 2.0

The simulate mode drives the blade along the trajectory from the bed as the ``simulate`` job does, for
``--start`` steps untimed, then times ``--steps`` steps phase by phase: each function the
stepper calls is wrapped by a timer (outermost call only, so ``_reach`` inside ``_sort`` counts
once), "other" is the rest of ``_advance`` (its own numpy and python). ``--save`` writes the
final state (positions, velocities, spin in id order) and the last step's contacts and
multipliers; ``--compare`` checks them array for array against such a file, written by other
code, so a change can be shown bit-identical. The build mode times every step of
``build_bed`` (bed length ``--length`` m, the rest of the config as given) and compares the
built bed the same way. Not a test: the figures depend on the machine.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np

# (owner, attribute, phase): the functions a step calls, by where the stepper looks them up.
PHASES = (
    ("stepper", "_sort", "sort + reorder"),
    ("stepper", "_reach", "reach"),
    ("broadphase", "slab_partition", "slab partition"),
    ("broadphase", "sphere_pairs", "sphere_pairs"),
    ("contacts", "body_contacts", "body_contacts"),
    ("contacts", "assemble", "assemble"),
    ("stepper", "_check_overlap", "check overlap"),
    ("WarmStart", "lookup", "warm lookup"),
    ("solver", "solve", "solve"),
    ("WarmStart", "store", "warm store"),
    ("contacts", "body_loads", "body_loads"),
    ("solver", "integrate", "integrate"),
    ("solver", "all_finite", "finite check"),
)


def instrument(totals: dict[str, float], last: dict[str, Any]) -> None:
    """Wrap the step's functions with timers adding seconds into ``totals`` per phase."""
    from dozerlab.ndem import broadphase, contacts, solver, stepper
    from dozerlab.ndem.warmstart import WarmStart

    owners = {
        "stepper": stepper,
        "broadphase": broadphase,
        "contacts": contacts,
        "solver": solver,
        "WarmStart": WarmStart,
    }
    depth = [0]

    def timed(fn: Callable[..., Any], phase: str) -> Callable[..., Any]:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            depth[0] += 1
            t0 = time.perf_counter()
            try:
                out = fn(*args, **kwargs)
            finally:
                depth[0] -= 1
            if depth[0] == 0:
                totals[phase] += time.perf_counter() - t0
            last[phase] = out
            return out

        return wrapper

    for owner, attr, phase in PHASES:
        setattr(owners[owner], attr, timed(getattr(owners[owner], attr), phase))
    advance = stepper._advance

    def whole(*args: Any) -> Any:
        t0 = time.perf_counter()
        out = advance(*args)
        totals["whole step"] += time.perf_counter() - t0
        totals["steps"] += 1
        return out

    stepper._advance = whole  # type: ignore[assignment]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bed", help="simulate mode: the bed (.npz)")
    ap.add_argument("--trajectory", help="simulate mode: the blade's trajectory (.csv)")
    ap.add_argument("--build", help="build mode: build this scenario's bed instead")
    ap.add_argument("--length", type=float, default=2.0, help="build mode: bed length (m)")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--start", type=int, default=150, help="untimed steps to mid-push")
    ap.add_argument("--steps", type=int, default=30, help="timed steps")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--save", help="write the final state and last contacts here (.npz)")
    ap.add_argument("--compare", help="check the final state against this file (.npz)")
    args = ap.parse_args(argv)

    from dozerlab.runtime import set_threads

    set_threads(args.threads)
    from dozerlab.config import load_config

    config = load_config(args.config)
    totals: dict[str, float] = defaultdict(float)
    last: dict[str, Any] = {}
    instrument(totals, last)
    if args.build:
        from dozerlab.scenarios.build import build_bed

        bed = build_bed(
            args.build, {**config, "bed": {**config["bed"], "length": args.length}}, progress=False
        )
        print(f"build {args.build}, {args.length} m: {bed.positions.shape[0]} spheres")
        result: dict[str, Any] = {"x": bed.positions, "r": bed.radii, "v": bed.velocities}
    else:
        result = _simulate(args, config, totals, last)
    steps = int(totals.pop("steps"))
    print(f"{steps} steps, {args.threads} thread(s)")
    phases = [phase for _, _, phase in PHASES]
    totals["other"] = totals["whole step"] - sum(totals[p] for p in phases)
    for phase in [*phases, "other", "whole step"]:
        print(f"{phase:16s} {1e3 * totals[phase] / steps:8.2f} ms/step")
    outside = totals["whole step"] - totals["solve"]
    print(f"{'outside solve':16s} {1e3 * outside / steps:8.2f} ms/step, {outside:.2f} s in all")
    if args.save:
        np.savez(args.save, **result)
    if args.compare:
        with np.load(args.compare, allow_pickle=False) as ref:
            bad = [k for k in result if k not in ref or not np.array_equal(result[k], ref[k])]
        print("bit-identical to", args.compare if not bad else f"DIFFERENT in {bad}")


def _simulate(
    args: argparse.Namespace, config: dict[str, Any], totals: dict[str, float], last: dict[str, Any]
) -> dict[str, Any]:
    """Drive the blade ``args.start`` steps, time ``args.steps``; the final state's arrays."""
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.blade import add_blade
    from dozerlab.scenarios.build import make_world
    from dozerlab.scenarios.trajectory import Trajectory

    if not (args.bed and args.trajectory):
        raise SystemExit("simulate mode needs --bed and --trajectory (or use --build)")
    traj, bed = Trajectory.load_csv(args.trajectory), Bed.load(args.bed)
    world, _ = make_world(bed, config)
    blade = add_blade(world, traj.position[0], config)
    for i in range(args.start + args.steps):
        if i == args.start:
            totals.clear()
        world.set_velocity(blade, traj.velocity[min(i, traj.steps - 1)])
        stats = world.step()
    state = world.state
    print(f"{state.n} spheres, {stats.contacts + stats.speculative} contacts mid-push")
    ci, cj, cd, gap, _ = last["assemble"]
    return {
        "x": state.public(state.x),
        "v": state.public(state.v),
        "w": state.public(state.w),
        "ci": state.id[ci],
        "cj": np.where(cj >= 0, state.id[np.maximum(cj, 0)], cj),
        "cd": cd,
        "gap": gap,
        "lam": state.warm.lam,
        "force": world.force_on(blade),
        "stats": np.array(
            [
                stats.contacts,
                stats.speculative,
                stats.max_overlap,
                stats.max_overlap_fraction,
                stats.residual,
            ]
        ),
    }


if __name__ == "__main__":
    main()
