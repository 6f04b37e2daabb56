"""``dozerlab reduce`` and ``compare-reduced``: the live reduced simulation and its comparison."""

from __future__ import annotations

import argparse

from dozerlab.cliargs import add_config, add_labels, add_run_inputs, add_threads, configure, labels


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reduce", help="run a sweep point with the reduced loop (learned fields + projection)"
    )
    add_run_inputs(p)
    _add_models(p)
    p.add_argument("--ndem", default=None, help="the point's NDEM field store (for replay)")
    add_config(p)
    p.add_argument("--out", required=True, help="field store to write (.zarr)")
    p.add_argument("--state", required=True, help="final particle state to write (.npz)")
    add_threads(p, help="numba/torch threads (default 1)")
    add_labels(p)
    p.set_defaults(func=_reduce)

    p = sub.add_parser(
        "reduce-points",
        help="run several sweep points with one pair of models in one process (the workflow's "
        "training-point runs), reading and writing the workflow's paths under --results",
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
    add_config(p)
    add_threads(p, help="numba/torch threads (default 1)")
    p.set_defaults(func=_reduce_points)

    p = sub.add_parser(
        "compare-reduced",
        help="measure a dynamics model's reduced runs against NDEM (held-out points)",
    )
    p.add_argument("--dynamics-model", required=True, help="dynamics model name (or replay)")
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
        f"reduced run: {metrics['reduced_steps']:.0f} steps in {metrics['wall_time_s']:.2f} s, "
        f"largest overlap {metrics['max_overlap']:.3f} of a radius -> {args.out}"
    )
    return 0


def _reduce_points(args: argparse.Namespace) -> int:
    from dozerlab import sweep as P

    points = [P.parse_point(text) for text in args.points]  # a misnamed one: ValueError, exit 2
    seen: dict[tuple[str, str], str] = {}
    for text, point in zip(args.points, points, strict=True):
        if point.key in seen:  # one run would be written twice, and counted twice
            raise ValueError(f"--points {seen[point.key]} and {text} are one point; give it once")
        seen[point.key] = text
    config = configure(args)
    from dozerlab.reduce.jobs import reduce_points_job

    runs = reduce_points_job(
        args.results, args.dynamics_model, points, config, args.dynamics, args.force_model
    )
    for text, metrics in zip(args.points, runs, strict=True):
        print(
            f"reduced run {text}: {metrics['reduced_steps']:.0f} steps in "
            f"{metrics['wall_time_s']:.2f} s, largest overlap {metrics['max_overlap']:.3f} of a radius"
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
