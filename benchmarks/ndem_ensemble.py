"""NDEM's own ensemble against the skill targets: how close NDEM's expected run comes to its run.

A model is scored against one NDEM run of each held-out point, beside that run's twin (the same
run from the bed with every grain moved a seeded 1 µm). The twin is one draw of NDEM's chaos,
and so is the run itself: the best any predictor can do is the *expected* run, the mean over
such draws, which still misses the run by the run's own chaotic part. This benchmark measures
that bound. For each point it runs more draws (``--seeds``: the workflow's twin command with
other jitter seeds), keeps them (``--keep``; draws already there are read, not run again), and
prints, beside the workflow's own twin and each model of ``results/reduced/{model}.json``:

- each draw against the run: the pushing force low-passed over 0.1 s (relative RMSE) and the
  final surface smoothed at one grain diameter (accuracy), as ``compare-reduced`` scores a
  twin — their spread is the spread of the skill's denominator;
- the ensemble mean of the draws (the mean low-passed force, the mean smoothed surface) against
  the run, for k = 1 … K draws (averaged over up to ``--subsets`` subsets of each size), and
  the limit k → ∞ of a fit err(k)² = a + b/k: the figure of the expected run itself;
- every figure also as a skill (over the workflow's twin's figure, as the workflow scores it),
  and each model's force error against the ensemble mean (how far it is from the expected force
  rather than from one draw of it).

If the run is a draw like the others, its error to the expected force is 1/√2 of a twin's, so a
force skill of at most 0.8 asks a model to come within about 0.37 twin errors of the expected
force (√(0.8² − 0.5) ≈ 0.37 in units of the twin's error), where the twin's skill is 1 by
definition and an ensemble of K draws reaches √((1 + 1/K)/2).

    python benchmarks/ndem_ensemble.py --results results --seeds 11 12 13 14 15 16 \
        --keep /tmp/ndem_ensemble --jobs 2

The workflow measures the expected run itself with ``reduced.twin.draws`` (the report's and
``compare-reduced``'s ``expected_*`` figures); this benchmark adds the subsets, the k → ∞ limit
and draws beyond the workflow's, without rerunning it.

The beds, trajectories, NDEM runs, twins and reduced runs come from a workflow's results folder
(the default sweep's); the default points are the config's held-out ones. Each draw is one
``python -m dozerlab simulate`` on one thread, ``--jobs`` of them at a time. Not a test.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.fields.store import open_store
from dozerlab.reduce.compare import (
    FORCE_WINDOW,
    height_accuracy,
    low_pass,
    reference,
    relative_rmse,
    smoothed_surface,
)
from dozerlab.scenarios.bed import Bed


def draw_paths(keep: Path, point: P.SweepPoint, seed: int) -> tuple[Path, Path]:
    """The kept store and final state of one draw."""
    stem = f"{P.point_name(point.speed, point.depth)}_seed~{seed}"
    return keep / point.scenario / f"{stem}.zarr", keep / point.scenario / f"{stem}.npz"


def simulate(
    results: Path, configfile: str, point: P.SweepPoint, jitter: float, seed: int, keep: Path
) -> str:
    """Run one draw (the workflow's twin command with ``seed``) unless it is kept already."""
    store, state = draw_paths(keep, point, seed)
    if state.exists():
        return f"{point.scenario} {point.speed}/{point.depth} seed {seed}: kept"
    state.parent.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "dozerlab",
        "simulate",
        "--bed",
        str(P.bed_path(results, point.scenario)),
        "--trajectory",
        str(P.trajectory_path(results, point)),
        "--scenario",
        point.scenario,
        "--speed",
        str(point.speed),
        "--depth",
        str(point.depth),
        "--config",
        configfile,
        "--out",
        str(store),
        "--state",
        str(state),
        "--threads",
        "1",
        "--jitter",
        str(jitter),
        "--jitter-seed",
        str(seed),
    ]
    # a draw is the benchmark's, not a run of the user's experiment: no MLflow record
    env = os.environ | {"NUMBA_NUM_THREADS": "1", "DOZERLAB_MLFLOW": "0"}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if done.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
    return f"{point.scenario} {point.speed}/{point.depth} seed {seed}: ran"


def lp_force(store: Path, row_dt: float) -> np.ndarray:
    """The pushing force (T,) N of a field store, low-passed over FORCE_WINDOW."""
    force = open_store(store)["force"].values.astype(np.float64)
    return low_pass(force[:, 0], row_dt, FORCE_WINDOW)


def subset_errors(
    members: np.ndarray, truth: np.ndarray, score: Any, subsets: int, rng: np.random.Generator
) -> list[float]:
    """The mean figure of the ensemble mean of k members, k = 1 … K (``members`` (K, …))."""
    k_all = members.shape[0]
    out = []
    for k in range(1, k_all + 1):
        combos = list(itertools.combinations(range(k_all), k))
        if len(combos) > subsets:
            combos = [combos[i] for i in rng.choice(len(combos), subsets, replace=False)]
        out.append(float(np.mean([score(members[list(c)].mean(axis=0), truth) for c in combos])))
    return out


def limit(errors: list[float]) -> float:
    """err(k)² = a + b/k fitted to ``errors`` (k = 1 …): √a, the error of k → ∞ draws."""
    k = np.arange(1, len(errors) + 1, dtype=np.float64)
    design = np.stack([np.ones_like(k), 1.0 / k], axis=1)
    (a, _), *_ = np.linalg.lstsq(design, np.square(errors), rcond=None)
    return float(np.sqrt(max(a, 0.0)))


def score_point(
    results: Path,
    config: dict[str, Any],
    point: P.SweepPoint,
    draws: list[tuple[Path, Path]],
    scored: dict[str, dict[tuple[str, float, float], dict[str, Any]]],
    subsets: int,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """Print and return one point's figures: the workflow's twin, the ``draws`` (kept stores and
    states), their ensemble means and each model of ``scored`` (its reduced JSON's entries)."""
    ref = reference(
        P.field_path(results, point),
        P.bed_path(results, point.scenario),
        P.state_path(results, point),
        config,
    )
    key = (point.scenario, point.speed, point.depth)
    warm = max((int(s[key].get("warmup_rows", 0)) for s in scored.values() if key in s), default=0)
    rows = slice(warm, None)  # the rows compare-reduced scores
    bed = ref.bed

    def surface(path: Path) -> np.ndarray:
        end = Bed.load(path)
        return smoothed_surface(end.positions, bed.radii, bed.length, bed.width, ref.sigma)

    def f_err(a: np.ndarray, b: np.ndarray) -> float:
        return relative_rmse(a, b)

    def s_acc(a: np.ndarray, b: np.ndarray) -> float:
        return height_accuracy(a, b, ref.surface_bed)

    truth_f = low_pass(ref.force[:, 0], ref.row_dt, FORCE_WINDOW)[rows]
    paths = [(P.twin_path(results, point), P.twin_path(results, point, "npz")), *draws]
    forces = np.stack([lp_force(z, ref.row_dt)[rows] for z, _ in paths])
    surfaces = np.stack([surface(n) for _, n in paths])
    each_fe = [f_err(f, truth_f) for f in forces]
    each_sa = [s_acc(s, ref.surface_ndem) for s in surfaces]
    twin_fe, twin_sa = each_fe[0], each_sa[0]
    ens_fe = subset_errors(forces, truth_f, f_err, subsets, rng)
    ens_sa = subset_errors(surfaces, ref.surface_ndem, s_acc, subsets, rng)
    # the surface's error fraction 1 − accuracy, fitted as the force's error is
    inf_fe, inf_sa = limit(ens_fe), 1.0 - limit([1.0 - a for a in ens_sa])
    # the expected run, estimated by the draws' mean: NDEM's run is not one of them
    expected_f, expected_s = forces.mean(axis=0), surfaces.mean(axis=0)
    run_fe, run_sa = f_err(truth_f, expected_f), s_acc(ref.surface_ndem, expected_s)
    k = forces.shape[0]
    print(
        f"\n{point.scenario} {point.speed}/{point.depth} ({point.role}; {k} draws: the twin first)"
    )
    print(f"  {'':<30} {'force lp err':>12} {'skill':>6} {'surface acc':>12} {'skill':>6}")

    def line(name: str, fe: float, sa: float, extra: str = "") -> None:
        skills = f"{fe / twin_fe:6.2f} {sa:12.3f} {sa / twin_sa:6.2f}"
        print(f"  {name:<30} {fe:12.3f} {skills}{extra}")

    line("twin (the workflow's)", twin_fe, twin_sa)
    line("draws, mean", float(np.mean(each_fe)), float(np.mean(each_sa)))
    line("draws, best", float(np.min(each_fe)), float(np.max(each_sa)))
    line("draws, worst", float(np.max(each_fe)), float(np.min(each_sa)))
    for j in sorted({2, 4, k}):
        if j <= k:
            line(f"ensemble mean of {j}", ens_fe[j - 1], ens_sa[j - 1])
    if k >= 3:  # two sizes fit a + b/k exactly: no limit to speak of
        line("ensemble mean, k -> inf (fit)", inf_fe, inf_sa)
    print(
        f"  NDEM's run to the ensemble's mean: force {run_fe:.3f}, surface {run_sa:.3f} "
        "(each model's to it after its own figures, the force also over NDEM's)"
    )
    entry: dict[str, Any] = {
        "role": point.role,
        "draws_force_lp_rel_rmse": each_fe,
        "draws_surface_accuracy": each_sa,
        "ensemble_force_lp_rel_rmse": ens_fe,
        "ensemble_surface_accuracy": ens_sa,
        "limit": {"force_lp_rel_rmse": inf_fe, "surface_accuracy": inf_sa} if k >= 3 else None,
        "ndem_to_ensemble_mean": {"force_lp_rel_rmse": run_fe, "surface_accuracy": run_sa},
        "models": {},
    }
    for m, by_point in scored.items():
        if key not in by_point:
            continue
        e = by_point[key]
        to_f = f_err(lp_force(P.reduced_path(results, m, point), ref.row_dt)[rows], expected_f)
        to_s = s_acc(surface(P.reduced_path(results, m, point, "npz")), expected_s)
        fe, sa = float(e["force_lp_rel_rmse"]), float(e["surface_accuracy"])
        line(m, fe, sa, f"   to the mean: {to_f:.3f} ({to_f / run_fe:.2f}x), {to_s:.3f}")
        entry["models"][m] = {
            "force_lp_rel_rmse": fe,
            "surface_accuracy": sa,
            "force_lp_rel_rmse_to_ensemble_mean": to_f,
            "surface_accuracy_to_ensemble_mean": to_s,
        }
    return entry


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--configfile", default="config/config.yaml")
    ap.add_argument(
        "--points", nargs="*", help="scenario:speed:depth (default: the held-out points)"
    )
    ap.add_argument("--seeds", type=int, nargs="+", required=True, help="jitter seeds of the draws")
    ap.add_argument("--keep", type=Path, required=True, help="folder of the draws (read or made)")
    ap.add_argument("--jobs", type=int, default=1, help="draws run at a time (one thread each)")
    ap.add_argument("--subsets", type=int, default=40, help="subsets of each size averaged")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()

    config = load_config(args.configfile)
    twin_cfg = config["reduced"]["twin"]
    if twin_cfg["seed"] in args.seeds:
        ap.error(f"seed {twin_cfg['seed']} is the workflow's twin (reduced.twin.seed): pick others")
    if args.points:
        points = [
            P.SweepPoint(s, float(v), float(d), "held-out")
            for s, v, d in (p.split(":") for p in args.points)
        ]
    else:
        points = [p for p in P.sweep_points(config) if p.role != "train"]
    scored = {}
    for m in config["reduced"]["dynamics_models"]:
        path = args.results / "reduced" / f"{m}.json"
        if path.exists():
            entries = json.loads(path.read_text())["points"]
            scored[m] = {(e["scenario"], float(e["speed"]), float(e["depth"])): e for e in entries}
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        futures = [
            pool.submit(
                simulate, args.results, args.configfile, p, twin_cfg["jitter_m"], s, args.keep
            )
            for p in points
            for s in args.seeds
        ]
        for f in futures:
            print(f.result(), flush=True)
    rng = np.random.default_rng(0)
    report = {}
    for point in points:
        draws = [draw_paths(args.keep, point, s) for s in args.seeds]
        entry = score_point(args.results, config, point, draws, scored, args.subsets, rng)
        report[f"{point.scenario} {point.speed}/{point.depth}"] = entry
        if args.json:
            args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
