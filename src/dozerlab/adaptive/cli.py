"""``dozerlab adaptive-points``, ``adaptive-record``, ``adaptive-curve``: an adaptive sweep's jobs."""

from __future__ import annotations

import argparse

from dozerlab.cliargs import add_command, add_config, add_threads, configure


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "adaptive-points",
        "write an adaptive sweep's round of points (round 0: the initial design)",
        "python -m dozerlab adaptive-points --round 1 --config config/adaptive.yaml \\\n"
        "      --previous results/adaptive/round~0/points.csv \\\n"
        "      --stores results/fields/hill/speed~0.75_depth~0.03.zarr … \\\n"
        "      --out results/adaptive/round~1/points.csv",
    )
    p.add_argument("--round", type=int, required=True, help="the round (0: the initial design)")
    add_config(p)
    p.add_argument(
        "--previous", nargs="*", default=[], help="points.csv of rounds 0 … round-1, in order"
    )
    p.add_argument(
        "--stores", nargs="*", default=[], help="field stores of the earlier rounds' NDEM runs"
    )
    p.add_argument("--out", required=True, help="points.csv to write")
    add_threads(p)
    p.set_defaults(func=_points)

    p = add_command(
        sub,
        "adaptive-record",
        "record a round of an adaptive sweep: its points and the models' held-out errors (JSON, MLflow)",
        "python -m dozerlab adaptive-record --config config/adaptive.yaml \\\n"
        "      --rounds results/adaptive/round~0/points.csv \\\n"
        "      --validations results/adaptive/round~0/validation/linear.json \\\n"
        "      --models results/adaptive/round~0/models/linear --results results \\\n"
        "      --out results/adaptive/round~0/record.json",
    )
    add_config(p)
    p.add_argument(
        "--rounds", nargs="+", required=True, help="points.csv of rounds 0 … r, in order"
    )
    p.add_argument(
        "--validations",
        nargs="*",
        default=[],
        help="validation JSONs of the models trained on rounds 0 … r",
    )
    p.add_argument(
        "--models",
        nargs="*",
        default=[],
        help="the round's model directories: their reduced-simulation figures (with --results)",
    )
    p.add_argument(
        "--results",
        help="the results folder holding the held-out points' runs, replay loops and twins",
    )
    p.add_argument("--out", required=True, help="record JSON to write")
    add_threads(p)
    p.set_defaults(func=_record)

    p = add_command(
        sub,
        "adaptive-curve",
        "the learning curve of an adaptive sweep against the grid and random designs (CSV, figures)",
        "python -m dozerlab adaptive-curve --config config/adaptive.yaml --results results \\\n"
        "      --rounds results/adaptive/round~0/points.csv results/adaptive/round~1/points.csv \\\n"
        "      --out results/adaptive/learning_curve.csv --plots results/adaptive/plots",
    )
    add_config(p)
    p.add_argument("--rounds", nargs="+", required=True, help="points.csv of every round, in order")
    p.add_argument(
        "--results", required=True, help="the results folder holding the runs' field stores"
    )
    p.add_argument("--out", required=True, help="learning-curve CSV to write")
    p.add_argument("--plots", required=True, help="folder of figures to write")
    add_threads(p)
    p.set_defaults(func=_curve)


def _points(args: argparse.Namespace) -> int:
    config = configure(args)
    from dozerlab.adaptive.jobs import points_job

    rows = points_job(config, args.round, args.previous, args.stores, args.out)
    for r in rows:
        print(f"round {args.round}: {r.point.scenario} {r.point.name} ({r.why})")
    return 0


def _record(args: argparse.Namespace) -> int:
    config = configure(args)
    from dozerlab.adaptive.jobs import record_job

    rec = record_job(
        config, args.rounds, args.validations, args.out, models=args.models, results=args.results
    )
    errors = ", ".join(f"{m} {100 * e:.1f} %" for m, e in rec["errors"].items())
    print(
        f"round {rec['round']}: {rec['runs']} NDEM training runs; held-out force_x rel. RMSE {errors or '-'}"
    )
    for m, fig in rec.get("reduced", {}).items():
        print(
            f"round {rec['round']}: {m} in the replay loop, low-passed force_x rel. RMSE "
            f"{100 * fig['reduced_force_lp_rel_rmse']:.1f} % (twin {100 * fig['twin_force_lp_rel_rmse']:.1f} %)"
        )
    return 0


def _curve(args: argparse.Namespace) -> int:
    config = configure(args)
    from dozerlab.adaptive.jobs import curve_job

    rows = curve_job(config, args.rounds, args.results, args.out, args.plots)
    print(f"learning curve: {len(rows)} rows -> {args.out}")
    return 0
