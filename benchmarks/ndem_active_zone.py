"""Faster NDEM designs against the full solve and against NDEM's own chaos, side by side.

For each point, runs of the simulate loop on the same bed, thread count and machine: the full
solve (every grain, all ``solver.iterations`` sweeps a step, no active zone), its twins (the
full solve from the bed with every grain moved a seeded 1 µm, one per ``--seeds``: NDEM's
run-to-run spread) and each design (``--designs``: solver settings over the config's). Printed
per point: wall time per simulated second of each, each design's speed-up over the full solve
(against the median of the full run and its twins, all full solves, which are interleaved with
the designs so that the machine's load reaches both alike), its awake fraction, its
contact-iterations relative to the full run's (≈ its sweeps a step over the full run's), and how
far each twin and design lands from the full run on the scales NDEM reproduces — the pushing
force low-passed over 0.1 s (relative RMSE, and the error of its mean over the pass) and the
final surface smoothed at one grain diameter (accuracy 1 − Σ|h − h_full| / Σ|h_full − h_bed|).
The twin floor is the worst twin on each figure; a design's run is marked ok where it is at least
as close to the full run as that floor on all three.

One chaotic run against the worst of a few twins is a weak test either way, so with
``--design-seeds`` each design also runs from the bed jittered as the twins' are (one run per
seed, beside its run from the bed itself), and each design's spread over its runs (min–max, mean)
is printed beside the twins'. Every one of these runs is compared with the one full run, so a
design that changes nothing but the chaos draws its figures from the twins' distribution. The
design passes where, on each of the three figures, its mean over its runs is no worse than the
worst twin: its typical run lands within the range chaos alone spans. Stricter rules are not
honest with three or four runs a side: a design identical to the full solve would have its mean
worse than the twins' mean on a given figure half the time, and its worst of four runs worse
than the worst of three twins four times in seven, so it would fail one of six such comparisons
most of the time. The printed spreads show how far inside or outside the range each figure lies.
What the departure is made of follows: the design's runs' spread against NDEM's draws' (the full
run and its twins), how far apart the two groups' means lie against what chaos alone would leave,
and its mean push against NDEM's (``departure``).

    python benchmarks/ndem_active_zone.py --results results --configfile config/config.yaml
    python benchmarks/ndem_active_zone.py --points hill:0.875:0.045 --threads 1 --seeds 1 2 3 \
        --designs zone tol3e-4:tolerance=3e-4 zone+tol1e-3:active_zone.enabled=true,tolerance=1e-3
    python benchmarks/ndem_active_zone.py --points hill:0.875:0.045 --seeds 1 2 3 \
        --designs tol3e-4:tolerance=3e-4 --design-seeds 1 2 3 --keep /tmp/tol --json tol.json

A design is NAME[:KEY=VALUE,...]: solver keys (``active_zone.margin`` for the nested ones);
the name ``zone`` alone is the active zone at the config's settings.

The beds and trajectories come from a workflow's results folder (``snakemake --cores 2
results/trajectories/...``); the default points are the config's held-out ones. Not a test:
the times depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def run(bed: Any, traj: Any, config: dict[str, Any], tmp: Path, name: str) -> dict[str, Any]:
    """One simulate loop; its loop wall time (s), force rows (T, 3) N, row period (s) and final
    positions (N, 3) m."""
    from dozerlab.fields.run import drive
    from dozerlab.fields.sampling import SamplingGrid
    from dozerlab.scenarios.bed import Bed

    grid = SamplingGrid.from_config(config)
    attrs = {"scenario": bed.scenario, "speed": traj.speed, "depth": None}
    state = tmp / f"{name}.npz"
    t0 = time.perf_counter()
    stats = drive(bed, traj, config, grid, attrs, tmp / f"{name}.zarr", state_out=state)
    wall = time.perf_counter() - t0
    every = int(config["sampling"]["every"])
    return {
        "loop_s": stats.wall_time,
        "wall_s": wall,
        "force": np.array(stats.forces).reshape(-1, 3),
        "row_dt": every * traj.dt,
        "positions": Bed.load(state).positions,
        "active_fraction": stats.metrics(bed.count)["active_fraction"],
        "contact_iterations": stats.contact_iterations,
    }


def agreement(a: dict[str, Any], ref: dict[str, Any], bed: Any, sigma: float) -> dict[str, float]:
    """How close run ``a`` lands to ``ref`` on the force low-passed over 0.1 s and the surface
    smoothed at ``sigma`` (m)."""
    from dozerlab.reduce.compare import height_accuracy, low_pass, relative_rmse, smoothed_surface

    fa = low_pass(a["force"][:, 0], a["row_dt"], 0.1)
    fr = low_pass(ref["force"][:, 0], ref["row_dt"], 0.1)
    mean_ref = float(ref["force"][:, 0].mean())

    def surface(pos: np.ndarray) -> np.ndarray:
        return smoothed_surface(pos, bed.radii, bed.length, bed.width, sigma)

    return {
        "force_lp_rel_rmse": relative_rmse(fa, fr),
        "force_mean_rel_err": abs(float(a["force"][:, 0].mean()) - mean_ref) / abs(mean_ref),
        "surface_accuracy": height_accuracy(
            surface(a["positions"]), surface(ref["positions"]), surface(bed.positions)
        ),
    }


def design_config(config: dict[str, Any], spec: str) -> tuple[str, dict[str, Any]]:
    """A design's name and config: ``NAME[:KEY=VALUE,...]`` over ``config``'s solver, the
    full solve's (no active zone) unless set; ``zone`` alone enables the active zone."""
    name, _, settings = spec.partition(":")
    cfg = copy.deepcopy(config)
    solver = cfg["solver"]
    solver["active_zone"]["enabled"] = name == "zone" and not settings
    for item in filter(None, settings.split(",")):
        key, _, value = item.partition("=")
        *outer, last = key.split(".")
        section = solver
        for k in outer:
            section = section[k]
        old = section[last]
        section[last] = (
            value.lower() == "true" if isinstance(old, bool) else type(old)(float(value))
        )
    return name, cfg


def passes(design: dict[str, float], floor: dict[str, float]) -> bool:
    """Whether a design lands at least as close to the full run as the twin floor does."""
    return (
        design["force_lp_rel_rmse"] <= floor["force_lp_rel_rmse"]
        and design["force_mean_rel_err"] <= floor["force_mean_rel_err"]
        and design["surface_accuracy"] >= floor["surface_accuracy"]
    )


FIGURES = ("force_lp_rel_rmse", "force_mean_rel_err", "surface_accuracy")


def worst(name: str, values: list[float]) -> float:
    """The worst of ``values`` on figure ``name``: the largest error, the least accuracy."""
    return min(values) if name == "surface_accuracy" else max(values)


def spread(figs: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Each figure's min, max, mean and worst over the runs ``figs``."""
    out = {}
    for name in FIGURES:
        values = [f[name] for f in figs]
        out[name] = {
            "min": min(values),
            "max": max(values),
            "mean": float(np.mean(values)),
            "worst": worst(name, values),
        }
    return out


def passes_spread(design: dict[str, dict[str, float]], twins: dict[str, dict[str, float]]) -> bool:
    """Whether a design's mean over its runs is no worse than the worst twin on every figure
    (``spread`` of each)."""
    for name in FIGURES:
        sign = -1.0 if name == "surface_accuracy" else 1.0
        if sign * design[name]["mean"] > sign * twins[name]["worst"]:
            return False
    return True


def departure(ndem: list[dict[str, Any]], design: list[dict[str, Any]]) -> dict[str, float]:
    """What a design's departure from NDEM is made of, on the pushing force low-passed over
    0.1 s: NDEM's draws (``ndem``: the full run and its twins) and the design's runs, at least
    two a group, each averaged over its runs. A run's spread about its group's mean (relative
    RMS over the pass, to NDEM's mean push): the chaos. How far apart the two means lie, over
    what chaos alone would leave between them (√(σ²_ndem/n + σ²_design/m)): above 1, a bias
    adds to the chaos. And the mean push over the pass (N, the magnitude of force x), the
    design's less NDEM's, also in standard errors of that difference."""
    from dozerlab.reduce.compare import low_pass

    rows = min(len(r["force"]) for r in ndem + design)

    def group(runs: list[dict[str, Any]]) -> tuple[np.ndarray, float, np.ndarray]:
        lp = np.array([low_pass(r["force"][:rows, 0], r["row_dt"], 0.1) for r in runs])
        var = float(((lp - lp.mean(axis=0)) ** 2).sum() / ((len(runs) - 1) * rows))
        push = np.array([abs(float(r["force"][:rows, 0].mean())) for r in runs])
        return lp.mean(axis=0), var, push

    mean_n, var_n, push_n = group(ndem)
    mean_d, var_d, push_d = group(design)
    scale = float(np.abs(mean_n).mean())
    apart = float(np.sqrt(((mean_d - mean_n) ** 2).mean()))
    chaos = float(np.sqrt(var_n / len(ndem) + var_d / len(design)))
    difference = float(push_d.mean() - push_n.mean())
    se = float(np.sqrt(push_n.var(ddof=1) / len(ndem) + push_d.var(ddof=1) / len(design)))
    return {
        "spread_ndem": float(np.sqrt(var_n)) / scale,
        "spread_design": float(np.sqrt(var_d)) / scale,
        "spread_ratio": float(np.sqrt(var_d / var_n)),
        "apart_over_chaos": apart / chaos,
        "push_ndem_n": float(push_n.mean()),
        "push_difference_n": difference,
        "push_difference_se": difference / se,
    }


def departure_line(label: str, name: str, d: dict[str, float]) -> str:
    """One printed row of :func:`departure`."""
    return (
        f"{label:<20} {name:<16} a run's spread {d['spread_design']:5.1%} against NDEM's "
        f"{d['spread_ndem']:5.1%} ({d['spread_ratio']:.2f}x); means apart "
        f"{d['apart_over_chaos']:.2f}x what chaos alone leaves; mean push "
        f"{d['push_difference_n']:+.0f} N ({d['push_difference_n'] / d['push_ndem_n']:+.1%}, "
        f"{d['push_difference_se']:+.1f} standard errors) against NDEM's {d['push_ndem_n']:.0f} N"
    )


def spread_line(label: str, name: str, sp: dict[str, dict[str, float]], ok: str) -> str:
    """One printed row of a spread: each figure's min–max and mean."""
    f, m, s = (sp[k] for k in FIGURES)
    return (
        f"{label:<20} {name:<16} "
        f"{f['min']:6.1%}–{f['max']:6.1%} ({f['mean']:6.1%})  "
        f"{m['min']:6.2%}–{m['max']:6.2%} ({m['mean']:6.2%})  "
        f"{s['min']:6.1%}–{s['max']:6.1%} ({s['mean']:6.1%})  {ok}"
    )


def line(
    label: str,
    name: str,
    r: dict[str, Any],
    full: dict[str, Any],
    full_s: float,
    sim_s: float,
    fig: dict[str, float],
    ok: str,
) -> str:
    """One printed row: run ``r`` (``full_s`` the full solves' median loop seconds, ``sim_s``
    the simulated seconds) and its agreement ``fig`` with the full run."""
    return (
        f"{label:<20} {name:<16} {r['loop_s'] / sim_s:8.2f} {full_s / r['loop_s']:7.2f}x "
        f"{r['active_fraction']:6.1%} "
        f"{r['contact_iterations'] / full['contact_iterations']:5.2f} "
        f"{fig['force_lp_rel_rmse']:6.1%} {fig['force_mean_rel_err']:6.2%} "
        f"{fig['surface_accuracy']:7.1%}  {ok}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="results", help="a workflow's results folder")
    parser.add_argument("--configfile", default="config/config.yaml")
    parser.add_argument(
        "--points", nargs="*", help="scenario:speed:depth (default: the held-out points)"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--jitter", type=float, default=1e-6, help="twins' jitter, m")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1], help="twins' jitter seeds")
    parser.add_argument(
        "--designs", nargs="+", default=["zone"], help="NAME[:KEY=VALUE,...] (solver settings)"
    )
    parser.add_argument(
        "--design-seeds",
        type=int,
        nargs="*",
        default=[],
        help="also run each design from the bed jittered with each of these seeds (as the twins)",
    )
    parser.add_argument("--json", help="also write the figures here (after every point)")
    parser.add_argument(
        "--keep",
        help="write each run's field store and final state under this new folder instead of a "
        "temporary one (an interrupted benchmark's finished runs can then still be compared)",
    )
    args = parser.parse_args()

    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory
    from dozerlab.sweep import SweepPoint, bed_path, by_role, sweep_points, trajectory_path

    threads = set_threads(args.threads)
    config = load_config(args.configfile)
    if args.points:
        points = [
            SweepPoint(s, float(v), float(d), "interpolation")
            for s, v, d in (p.split(":") for p in args.points)
        ]
    else:
        every = sweep_points(config)
        points = by_role(every, "interpolation") + by_role(every, "extrapolation")
    full_cfg = copy.deepcopy(config)
    full_cfg["solver"]["active_zone"]["enabled"] = False
    full_cfg["solver"]["tolerance"] = 0.0
    designs = [design_config(config, spec) for spec in args.designs]
    print(
        f"threads {threads}; full solve {full_cfg['solver']['iterations']} sweeps; twin jitter "
        f"{args.jitter} m, seeds {args.seeds}; designs {args.designs}, from the bed and from "
        f"its jitters {args.design_seeds}"
    )
    header = (
        f"{'point':<20} {'run':<16} {'s/sim s':>8} {'speed-up':>8} {'awake':>6} {'c-it':>5} "
        f"{'F_lp':>6} {'mean F':>6} {'surface':>7}  ok"
    )
    rows = []
    for point in points:
        bed = Bed.load(bed_path(args.results, point.scenario))
        traj = Trajectory.load_csv(trajectory_path(args.results, point))
        sim_s = traj.steps * traj.dt
        sigma = 2.0 * float(np.mean(bed.radii))
        label = f"{point.scenario} {point.speed}/{point.depth}"
        twins: dict[int, dict[str, Any]] = {}
        # run name -> (design, jitter seed or None for the bed itself, the run)
        runs: dict[str, tuple[str, int | None, dict[str, Any]]] = {}
        keep = (
            Path(args.keep) / f"{point.scenario}_{point.speed}_{point.depth}" if args.keep else None
        )
        if keep:
            keep.mkdir(parents=True)
        with contextlib.nullcontext(str(keep)) if keep else tempfile.TemporaryDirectory() as tmp:
            full = run(bed, traj, full_cfg, Path(tmp), "full")
            print(f"  {label}: full {full['loop_s'] / sim_s:.2f} s/sim s", flush=True)
            # Designs and twins alternate so that the load of a shared machine reaches both.
            queue: list[tuple[str, str | None, dict[str, Any], int | None]] = [
                (n if s is None else f"{n}@s{s}", n, c, s)
                for s in [None, *args.design_seeds]
                for n, c in designs
            ]
            step = max(1, len(queue) // max(1, len(args.seeds)))
            for i, seed in enumerate(args.seeds):
                queue.insert(
                    min(i * (step + 1) + 1, len(queue)), (f"twin{seed}", None, full_cfg, seed)
                )
            for name, design, cfg, seed in queue:
                start = bed if seed is None else bed.jittered(args.jitter, seed)
                done = run(start, traj, cfg, Path(tmp), name)
                if design is None and seed is not None:
                    twins[seed] = done
                elif design is not None:
                    runs[name] = (design, seed, done)
                print(f"  {label}: {name} {done['loop_s'] / sim_s:.2f} s/sim s", flush=True)
        full_s = float(np.median([full["loop_s"]] + [t["loop_s"] for t in twins.values()]))
        twin_fig = {seed: agreement(t, full, bed, sigma) for seed, t in twins.items()}
        floor = {
            "force_lp_rel_rmse": max(f["force_lp_rel_rmse"] for f in twin_fig.values()),
            "force_mean_rel_err": max(f["force_mean_rel_err"] for f in twin_fig.values()),
            "surface_accuracy": min(f["surface_accuracy"] for f in twin_fig.values()),
        }
        print(header)

        print(f"{label:<20} {'full':<16} {full['loop_s'] / sim_s:8.2f}")
        for seed, fig in twin_fig.items():
            print(line(label, f"twin{seed}", twins[seed], full, full_s, sim_s, fig, ""), flush=True)
        print(
            f"{label:<20} {'twin floor':<16} {'':8} {'':8} {'':6} {'':5} "
            f"{floor['force_lp_rel_rmse']:6.1%} {floor['force_mean_rel_err']:6.2%} "
            f"{floor['surface_accuracy']:7.1%}"
        )
        figures = {}
        for name, (_, seed, r) in runs.items():
            fig = agreement(r, full, bed, sigma)
            ok = passes(fig, floor)
            figures[name] = {
                "jitter_seed": seed,
                "s_per_s": r["loop_s"] / sim_s,
                "speedup": full_s / r["loop_s"],
                "active_fraction": r["active_fraction"],
                "contact_iterations_vs_full": r["contact_iterations"] / full["contact_iterations"],
                "ok": ok,
            } | fig
            print(line(label, name, r, full, full_s, sim_s, fig, "yes" if ok else "NO"), flush=True)
        twin_spread = spread(list(twin_fig.values()))
        spreads: dict[str, Any] = {}
        if args.design_seeds:
            print(
                f"{'point':<20} {'spread':<16} {'F_lp min–max (mean)':>26}  "
                f"{'mean F min–max (mean)':>29}  {'surface min–max (mean)':>26}  ok: mean no "
                "worse than the worst twin"
            )
            print(spread_line(label, f"twins ({len(twin_fig)})", twin_spread, ""))
            for design, _ in designs:
                mine = [figures[n] for n, (d, _, _) in runs.items() if d == design]
                sp = spread(mine)
                ok = passes_spread(sp, twin_spread)
                spreads[design] = {
                    "runs": len(mine),
                    "speedup_mean": float(np.mean([f["speedup"] for f in mine])),
                    "ok": ok,
                } | sp
                print(
                    spread_line(label, f"{design} ({len(mine)})", sp, "yes" if ok else "NO"),
                    flush=True,
                )
            # the full run and its twins against each design's runs, each group's mean over
            # its draws: how much of the departure is a wider spread, how much a bias
            draws = [full, *twins.values()]
            for design, _ in designs:
                mine_runs = [r for d, _, r in runs.values() if d == design]
                if len(draws) > 1 and len(mine_runs) > 1:
                    spreads[design]["departure"] = dep = departure(draws, mine_runs)
                    print(departure_line(label, design, dep), flush=True)
        rows.append(
            {
                "point": label,
                "full_s_per_s": full["loop_s"] / sim_s,
                "full_solves_median_s_per_s": full_s / sim_s,
                "twins": {
                    str(seed): fig | {"s_per_s": twins[seed]["loop_s"] / sim_s}
                    for seed, fig in twin_fig.items()
                },
                "twin_floor": floor,
                "twin_spread": twin_spread,
                "designs": figures,
                "design_spreads": spreads,
            }
        )
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
