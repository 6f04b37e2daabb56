"""An evolution model's settings chosen by cross-validation on the training points alone.

    python benchmarks/dynamics_select.py --results results [--config config/config.yaml] \\
        [--model ridge] [--folds speed] [--threads 1] \\
        "default:" "no bands:dynamics.ridge_z_bands=[]" "one row:dynamics.ridge_horizon=1"

Each argument is a variant, ``NAME:KEY=VALUE,...`` (dotted config keys, values as YAML), laid
over ``--config`` and validated like it (``reduce_settings.py``'s syntax). The sweep's training
points are split into folds by ``--folds`` (``speed``, ``depth`` or ``scenario``: one fold per
value, so every fold is a part of the training grid's range that the rest does not cover). For
each fold and variant, model ``--model`` is trained as rule ``train_dynamics`` trains it on the
other folds' NDEM stores (``train-dynamics``'s job, MLflow off), and the reduced loop runs on the
fold's points as rule ``reduce_points`` runs it (``reduce_run``, one thread); its final
surface smoothed at one grain diameter is scored against the point's NDEM run
(``compare_point``, ``surface_accuracy``). Every training point is thus scored once by models
that never saw it, and the sweep's held-out points are not used at all: the figures can choose
a default without looking at the points the report scores it on.

Prints each loop's accuracy as it comes, then per variant the accuracy per fold, its mean over
the training points, how many points it is the best of, and the ranking. The variants alternate
fold by fold, so machine noise falls on all of them alike. Reads ``--results`` only (its beds,
trajectories, NDEM stores and states, and the replay force model, whose figures are not
reported: the loop's grains never read the force).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.runtime import set_threads
from reduce_settings import variant

FOLDS = {"speed": lambda p: p.speed, "depth": lambda p: p.depth, "scenario": lambda p: p.scenario}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("variants", nargs="+", help="NAME:KEY=VALUE,... (see the module doc)")
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--model", default="ridge", choices=("ridge", "unet", "persistence"))
    ap.add_argument("--folds", default="speed", choices=sorted(FOLDS))
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    os.environ["DOZERLAB_MLFLOW"] = "0"
    set_threads(args.threads)
    from dozerlab.learn.dynamics.jobs import train_dynamics_job
    from dozerlab.reduce.compare import compare_point
    from dozerlab.reduce.models import ForcePredictor, load_field_model
    from dozerlab.reduce.run import reduce_run

    base = load_config(args.config)
    variants = [variant(text, base) for text in args.variants]
    res = args.results
    points = [p for p in P.sweep_points(base) if p.role == "train"]
    key = FOLDS[args.folds]
    folds = sorted({key(p) for p in points})
    if len(folds) < 2:
        raise SystemExit(f"--folds {args.folds}: the training points hold one value only")
    force = ForcePredictor(P.reduce_force_model_path(res, base["reduced"], "replay"))
    grid = tuple(base["sampling"]["bins"])
    acc: dict[str, dict[tuple[str, str], float]] = {n: {} for n, _ in variants}
    with tempfile.TemporaryDirectory() as tmp:
        for fold in folds:
            seen = [p for p in points if key(p) != fold]
            unseen = [p for p in points if key(p) == fold]
            for vi, (name, cfg) in enumerate(variants):
                out = Path(tmp) / f"model-{fold}-{vi}"
                t0 = time.perf_counter()
                fit = train_dynamics_job(
                    args.model, [P.field_path(res, p) for p in seen], cfg, out, progress=False
                )
                trained = time.perf_counter() - t0
                kept = "" if fit.penalty is None else f", penalty {fit.penalty:g}"
                for pt in unseen:
                    model = load_field_model(out, grid)
                    store, state = Path(tmp) / "run.zarr", Path(tmp) / "run.npz"
                    r = reduce_run(
                        P.bed_path(res, pt.scenario),
                        P.trajectory_path(res, pt),
                        cfg,
                        model,
                        force,
                        store,
                        state,
                        scenario=pt.scenario,
                        speed=pt.speed,
                        depth=pt.depth,
                    )
                    m, _ = compare_point(
                        P.field_path(res, pt),
                        store,
                        P.bed_path(res, pt.scenario),
                        P.state_path(res, pt),
                        state,
                        cfg,
                    )
                    acc[name][pt.key] = m["surface_accuracy"]
                    print(
                        f"{name:>12} fold {args.folds} {fold} (trained on {len(seen)} points in "
                        f"{trained:.0f} s{kept}): {pt.scenario} {pt.speed}/{pt.depth} loop "
                        f"{r['wall_time_s']:.2f} s, largest overlap {r['max_overlap']:.3f} r, "
                        f"smoothed-surface accuracy {m['surface_accuracy']:.3f}",
                        flush=True,
                    )
    keys = [p.key for p in points]
    table = np.array([[acc[n][k] for k in keys] for n, _ in variants])  # (variants, points)
    wins = np.bincount(table.argmax(axis=0), minlength=len(variants))
    by_fold = {f: [keys.index(p.key) for p in points if key(p) == f] for f in folds}
    for i, (name, _) in enumerate(variants):
        per_fold = ", ".join(f"{f}: {table[i, idx].mean():.3f}" for f, idx in by_fold.items())
        print(
            f"{name}: smoothed-surface accuracy on the unseen folds ({per_fold}), mean "
            f"{table[i].mean():.3f} over {len(keys)} points, best at {wins[i]}"
        )
    order = np.argsort(-table.mean(axis=1))
    print("ranking: " + " > ".join(variants[i][0] for i in order))


if __name__ == "__main__":
    main()
