"""``dozerlab reduce`` and ``compare-reduced``: the live reduced simulation and its comparison."""

from __future__ import annotations

import argparse
from pathlib import PurePosixPath

from dozerlab.cliargs import (
    add_command,
    add_config,
    add_labels,
    add_run_inputs,
    add_threads,
    configure,
    labels,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "reduce",
        "run a sweep point with the reduced loop (learned fields + projection)",
        "python -m dozerlab reduce --config config/quick.yaml --bed results/beds/hill.npz \\\n"
        "      --trajectory results/trajectories/hill/speed~1.25_depth~0.06.csv \\\n"
        "      --ndem results/fields/hill/speed~1.25_depth~0.06.zarr \\\n"
        "      --dynamics results/dynamics/ridge --force-model results/reduced/ridge/force_model \\\n"
        "      --out results/reduced/ridge/hill/speed~1.25_depth~0.06.zarr \\\n"
        "      --state results/reduced/ridge/hill/speed~1.25_depth~0.06.npz",
    )
    add_run_inputs(p)
    _add_models(p)
    p.add_argument("--ndem", default=None, help="the point's NDEM store (replay plays it back)")
    add_config(p)
    p.add_argument("--out", required=True, help="field store to write (.zarr)")
    p.add_argument("--state", required=True, help="final particle state to write (.npz)")
    add_threads(p, help="numba/torch threads (default 1)")
    add_labels(p)
    p.set_defaults(func=_reduce)

    p = add_command(
        sub,
        "reduce-points",
        "run the reduced loop on several sweep points in one process, on the paths under --results",
        "python -m dozerlab reduce-points --config config/quick.yaml --results results \\\n"
        "      --dynamics-model ridge --dynamics results/dynamics/ridge \\\n"
        "      --force-model results/models/linear \\\n"
        "      --points hill/speed~1.0_depth~0.04 hill/speed~1.5_depth~0.04",
    )
    p.add_argument("--results", default="results", help="the workflow's results folder")
    p.add_argument(
        "--dynamics-model",
        required=True,
        help="the dynamics model's name: the runs go to RESULTS/reduced/NAME/",
    )
    _add_models(p)
    p.add_argument(
        "--points",
        nargs="+",
        required=True,
        help="the points, each as SCENARIO/speed~V_depth~D (the stem of its result paths)",
    )
    p.add_argument(
        "--rule",
        choices=("reduce", "reduce_training_points"),
        default="reduce",
        help="the workflow rule the runs are tagged with in MLflow (default reduce)",
    )
    add_config(p)
    add_threads(p, help="numba/torch threads (default 1)")
    p.set_defaults(func=_reduce_points)

    p = add_command(
        sub,
        "compare-reduced",
        "measure a dynamics model's reduced runs against NDEM on the held-out points",
        "python -m dozerlab compare-reduced --dynamics-model ridge --config config/quick.yaml \\\n"
        "      --results results --out results/reduced/ridge.json \\\n"
        "      --plots results/reduced/ridge/compare",
    )
    p.add_argument("--dynamics-model", required=True, help="model name, or replay (NDEM's fields)")
    add_config(p)
    p.add_argument("--results", default="results", help="the workflow's results folder")
    p.add_argument("--out", required=True, help="JSON to write (results/reduced/NAME.json)")
    p.add_argument("--plots", required=True, help="folder for the plots and animations")
    p.add_argument("--no-animation", action="store_true", help="skip the GIFs")
    p.set_defaults(func=_compare)


def _add_models(p: argparse.ArgumentParser) -> None:
    """``--dynamics`` and ``--force-model``: the two learned parts a reduced run loads."""
    p.add_argument(
        "--dynamics",
        required=True,
        help="field-evolution model: an MLflow pyfunc directory (results/dynamics/NAME) or "
        "'replay' (the point's NDEM fields)",
    )
    p.add_argument(
        "--force-model", required=True, help="force model directory (results/models/NAME)"
    )


def _reduce(args: argparse.Namespace) -> int:
    config = configure(args)
    from dozerlab.reduce.jobs import reduce_job

    metrics = reduce_job(
        args.bed,
        args.trajectory,
        config,
        args.dynamics,
        args.force_model,
        args.out,
        args.state,
        ndem_store=args.ndem,
        **labels(args),
    )
    print(
        f"reduced run: {metrics['reduced_rows']:.0f} rows in {metrics['reduced_steps']:.0f} steps, "
        f"{metrics['wall_time_s']:.2f} s, "
        f"largest overlap {metrics['max_overlap']:.3f} of a radius -> {args.out}"
    )
    return 0


def _reduce_points(args: argparse.Namespace) -> int:
    from dozerlab import sweep as P
    from dozerlab.runtime import check_name

    for text in args.points:
        parts = PurePosixPath(text).parts
        if len(parts) != 2:
            raise ValueError(f"--points {text!r} is not SCENARIO/speed~V_depth~D")
        check_name(parts[0], "--points scenario")
    points = [P.parse_point(text) for text in args.points]  # a misnamed one: ValueError, exit 2
    seen: dict[tuple[str, str], str] = {}
    for text, point in zip(args.points, points, strict=True):
        if point.key in seen:  # one run would be written twice, and counted twice
            raise ValueError(f"--points {seen[point.key]} and {text} are one point; give it once")
        seen[point.key] = text
    config = configure(args)
    from dozerlab.reduce.jobs import reduce_points_job

    runs = reduce_points_job(
        args.results,
        args.dynamics_model,
        points,
        config,
        args.dynamics,
        args.force_model,
        args.rule,
    )
    for text, metrics in zip(args.points, runs, strict=True):
        print(
            f"reduced run {text}: {metrics['reduced_rows']:.0f} rows in "
            f"{metrics['reduced_steps']:.0f} steps, {metrics['wall_time_s']:.2f} s, largest overlap {metrics['max_overlap']:.3f} of a radius"
        )
    return 0


def _compare(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.reduce.jobs import compare_job

    summary = compare_job(
        args.dynamics_model,
        load_config(args.config),
        args.results,
        args.out,
        args.plots,
        animation=not args.no_animation,
    )
    for role, agg in summary["overall"].items():
        print(f"{args.dynamics_model} {role}: " + ", ".join(f"{k} {v:.4g}" for k, v in agg.items()))
    return 0
