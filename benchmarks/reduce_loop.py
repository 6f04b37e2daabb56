"""The reduced loop against NDEM on one sweep point, side by side: same bed, trajectory, threads
and machine, in one process run.

    python benchmarks/reduce_loop.py --results results --scenario hill --speed 0.875 \\
        --depth 0.045 [--config config/config.yaml] [--threads 1] [--dynamics replay ridge] \\
        [--chaos] [--stored-ndem] [--repeat 3]

Runs NDEM (``fields.jobs.simulate``) on the point's bed and trajectory under ``--results``, then
the reduced loop with each dynamics model (``replay``: the new NDEM run's own fields;
otherwise ``results/dynamics/{model}``) and the force model rule ``reduce`` gives it
(``sweep.reduce_force_model_path``: with ``reduced.force_fields`` loop the one fitted to that
model's loop fields), the heap frozen once they are loaded as the reduce job freezes it, into a
temporary folder, and prints for each: the stepping loop's wall time and its speed-up over
NDEM's (per simulated second: the same trajectory), the mean time per store row of each phase
(selection, advection, projection, sampling, field and force inference, store writes) and of
the NDEM warm-up, the grains moved per step, the largest overlap, and the comparison's accuracy
figures (and on the scales NDEM reproduces: the surface smoothed at one grain diameter, the
pushing force low-passed over 0.1 s);
with ``--chaos``, the same figures for a second NDEM run from the bed moved by 1 µm first.
With ``--stored-ndem`` the point's NDEM run already under ``--results`` (its store and final
state, read only) stands in for a new one: the speed-up is then against the stored store's
``wall_time_s``, measured when that run was made, not side by side.
With ``--repeat N`` NDEM and the loops run N times in turn (NDEM, each loop, NDEM, ...), so
the machine's drift falls on both alike, and the last line gives each loop's median speed-up
over the N pairs, the issue's figure measured side by side: one pair a point moved by up to
16 % between runs on a shared 2-core machine (BENCHMARKS.md). The accuracy figures are those
of the first round (the runs are deterministic).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.runtime import freeze_heap, set_threads


def _accuracy(c: dict[str, Any]) -> str:
    return (
        f"height accuracy {c['height_accuracy']:.3f}, force x rel. RMSE "
        f"{c['force_x_rel_rmse']:.3f}, velocity rel. L2 {c['velocity_rel_l2']:.3f}, "
        f"density rel. L2 {c['density_rel_l2']:.3f}, EMD {1e3 * c['final_emd_m']:.1f} mm"
    )


def _scales(
    bed: Path, ndem_store: Path, ndem_state: Path, store: Path, state: Path
) -> tuple[float, float]:
    """The accuracy of the final surface smoothed at one grain diameter and the relative RMSE
    of the pushing force low-passed over 0.1 s, against NDEM's run (the scales NDEM
    reproduces)."""
    from dozerlab.fields.store import open_store
    from dozerlab.reduce.compare import height_accuracy, low_pass, relative_rmse, smoothed_surface
    from dozerlab.scenarios.bed import Bed

    b = Bed.load(bed)
    sigma = 2.0 * float(np.mean(b.radii))

    def surface(positions: np.ndarray) -> np.ndarray:
        return smoothed_surface(positions, b.radii, b.length, b.width, sigma)

    acc = height_accuracy(
        surface(Bed.load(state).positions),
        surface(Bed.load(ndem_state).positions),
        surface(b.positions),
    )
    nd, rd = open_store(ndem_store), open_store(store)
    t = nd["time"].values
    fn, fr = (s["force"].values[:, 0].astype(np.float64) for s in (nd, rd))
    dt = float(t[1] - t[0])
    return acc, relative_rmse(low_pass(fr, dt, 0.1), low_pass(fn, dt, 0.1))


def point_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments naming a sweep point's inputs: --results, --config, --scenario, --speed,
    --depth (also benchmarks/reduce_overlaps.py's)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--results", default="results")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--speed", type=float, required=True)
    ap.add_argument("--depth", type=float, required=True)
    return ap


def main() -> None:
    ap = point_parser(__doc__)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--dynamics", nargs="+", default=["replay"])
    ap.add_argument(
        "--chaos",
        action="store_true",
        help="also score a second NDEM run from the bed moved by 1 µm: what two NDEM runs that "
        "differ by nothing disagree by (the floor of every figure)",
    )
    ap.add_argument(
        "--stored-ndem",
        action="store_true",
        help="compare against the point's NDEM store and state under --results instead of "
        "running NDEM again (minutes on the default sweep); its wall_time_s is not side by side",
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="rounds of NDEM and the loops in turn; the last line gives each loop's median "
        "speed-up over them",
    )
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error(f"--repeat must be >= 1, got {args.repeat}")
    if args.repeat > 1 and args.stored_ndem:
        ap.error("--repeat needs NDEM run side by side, not --stored-ndem")
    os.environ["DOZERLAB_MLFLOW"] = "0"
    set_threads(args.threads)
    from dozerlab.fields.jobs import simulate
    from dozerlab.fields.store import open_store
    from dozerlab.reduce.compare import compare_point

    cfg = load_config(args.config)
    point = P.SweepPoint(args.scenario, args.speed, args.depth)
    res = Path(args.results)
    bed, traj = P.bed_path(res, point.scenario), P.trajectory_path(res, point)
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        print(f"{point.scenario} {point.name}, {args.threads} thread(s)")
        speedups: dict[str, list[float]] = {name: [] for name in args.dynamics}
        for round_ in range(args.repeat):
            first = round_ == 0
            if args.repeat > 1:
                print(f"round {round_ + 1} of {args.repeat}")
            if args.stored_ndem:
                ndem_store, ndem_state = P.field_path(res, point), P.state_path(res, point)
                m = {"wall_time_s": float(open_store(ndem_store).attrs["wall_time_s"])}
                print(f"NDEM (stored {ndem_store}): loop {m['wall_time_s']:.2f} s")
            else:
                ndem_store, ndem_state = t / f"ndem{round_}.zarr", t / f"ndem{round_}.npz"
                t0 = time.perf_counter()
                m = simulate(bed, traj, cfg, ndem_store, state_out=ndem_state)
                print(f"NDEM: loop {m['wall_time_s']:.2f} s, job {time.perf_counter() - t0:.2f} s")
            if args.chaos and first:
                _chaos(bed, traj, cfg, t, ndem_store, ndem_state)
            for name in args.dynamics:
                r = run_loop(name, res, cfg, point, bed, traj, ndem_store, t / f"{name}{round_}")
                speedups[name].append(m["wall_time_s"] / r["wall_time_s"])
                phases = ", ".join(f"{k[3:]} {v:.2f}" for k, v in r.items() if k.startswith("ms_"))
                print(
                    f"{name}: loop {r['wall_time_s']:.2f} s ({speedups[name][-1]:.1f}x NDEM's), "
                    f"job {r['job_s']:.2f} s (models loaded before); NDEM warm-up "
                    f"{r['warmup_s']:.2f} s; ms per row: {phases}; grains moved per step "
                    f"{r['active_grains_mean']:.0f}; projection sweeps per step "
                    f"{r.get('projection_sweeps_mean', float('nan')):.1f}; largest overlap "
                    f"{r['max_overlap']:.3f} r"
                )
                if first:
                    out = t / f"{name}{round_}"
                    c, _ = compare_point(
                        ndem_store,
                        out.with_suffix(".zarr"),
                        bed,
                        ndem_state,
                        out.with_suffix(".npz"),
                        cfg,
                    )
                    acc, flp = _scales(
                        bed,
                        ndem_store,
                        ndem_state,
                        out.with_suffix(".zarr"),
                        out.with_suffix(".npz"),
                    )
                    print(f"    {_accuracy(c)}")
                    print(f"    smoothed surface {acc:.3f}, low-passed force x rel. RMSE {flp:.3f}")
        if args.repeat > 1:
            print(
                "median speed-up over the rounds: "
                + ", ".join(
                    f"{name} {np.median(v):.1f}x ({', '.join(f'{x:.1f}' for x in v)})"
                    for name, v in speedups.items()
                )
            )


def _chaos(
    bed: Path, traj: Path, cfg: dict[str, Any], t: Path, ndem_store: Path, ndem_state: Path
) -> None:
    """Score a second NDEM run from ``bed`` moved by 1 µm against the first (the floor)."""
    from dozerlab.fields.jobs import simulate
    from dozerlab.reduce.compare import compare_point
    from dozerlab.scenarios.bed import Bed

    moved = Bed.load(bed)
    rng = np.random.default_rng(0)
    moved.positions = moved.positions + rng.normal(scale=1e-6, size=moved.positions.shape)
    moved.save(t / "bed_moved.npz")
    simulate(t / "bed_moved.npz", traj, cfg, t / "chaos.zarr", state_out=t / "chaos.npz")
    c, _ = compare_point(ndem_store, t / "chaos.zarr", bed, ndem_state, t / "chaos.npz", cfg)
    acc, flp = _scales(bed, ndem_store, ndem_state, t / "chaos.zarr", t / "chaos.npz")
    print(f"chaos floor (NDEM from the bed moved by 1 µm): {_accuracy(c)}")
    print(f"    smoothed surface {acc:.3f}, low-passed force x rel. RMSE {flp:.3f}")


def run_loop(
    name: str,
    res: Path,
    cfg: dict[str, Any],
    point: P.SweepPoint,
    bed: Path,
    traj: Path,
    ndem_store: Path,
    out: Path,
) -> dict[str, Any]:
    """The reduced loop of dynamics model ``name`` on ``point`` into ``out``.zarr / .npz, as
    rule ``reduce`` runs it; its metrics with ``job_s``, the run's wall time with the models
    loaded before."""
    from dozerlab.reduce.models import ForcePredictor, load_field_model
    from dozerlab.reduce.run import reduce_run

    source = name if name == "replay" else P.dynamics_model_path(res, name)
    fm = load_field_model(source, tuple(cfg["sampling"]["bins"]), ndem_store)
    force = ForcePredictor(P.reduce_force_model_path(res, cfg["reduced"], name))
    freeze_heap()  # as the reduce job does: no full collection walks the models mid-loop
    t0 = time.perf_counter()
    r = reduce_run(
        bed,
        traj,
        cfg,
        fm,
        force,
        out.with_suffix(".zarr"),
        out.with_suffix(".npz"),
        scenario=point.scenario,
        speed=point.speed,
        depth=point.depth,
    )
    return {**r, "job_s": time.perf_counter() - t0}


if __name__ == "__main__":
    main()
