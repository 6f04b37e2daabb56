"""``dozerlab train``, ``validate`` and ``evaluate``: the learning commands."""

from __future__ import annotations

import argparse

from dozerlab.learn.names import MODEL_NAMES


def add_held_out(p: argparse.ArgumentParser) -> None:
    """The held-out stores' options of a validation command."""
    for name, what in (
        ("interpolation", "held-out stores inside the training ranges"),
        ("extrapolation", "held-out stores outside them"),
    ):
        p.add_argument(f"--{name}", nargs="*", default=[], metavar="F.zarr", help=what)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train one force/torque model on field stores")
    p.add_argument("--model", required=True, choices=MODEL_NAMES, help="model name")
    p.add_argument(
        "--train", required=True, nargs="+", metavar="F.zarr", help="training field stores"
    )
    p.add_argument(
        "--config", default=None, help="YAML file or inline JSON (default: all defaults)"
    )
    p.add_argument("--out", required=True, help="model directory to write (results/models/NAME)")
    p.add_argument(
        "--threads", type=int, default=None, help="thread budget (default: config threads.train)"
    )
    p.add_argument(
        "--device", default=None, help="torch device (default: cuda if present, else cpu)"
    )
    p.set_defaults(func=_train)

    p = sub.add_parser("validate", help="metrics and plots of a model on held-out sweep points")
    p.add_argument("--model", required=True, help="model directory (results/models/NAME)")
    add_held_out(p)
    p.add_argument(
        "--out",
        required=True,
        help="JSON to write (results/validation/NAME.json)",
    )
    p.add_argument(
        "--plots", default=None, help="plot folder (default: the JSON path without .json)"
    )
    p.add_argument("--config", default=None, help="YAML file or inline JSON (mlflow section)")
    p.add_argument("--threads", type=int, default=1, help="thread budget")
    p.set_defaults(func=_validate)

    p = sub.add_parser("evaluate", help="print a model's metrics on field stores")
    p.add_argument("--model", required=True, help="model directory")
    p.add_argument("stores", nargs="+", metavar="STORE", help="field stores")
    p.add_argument("--threads", type=int, default=1, help="thread budget")
    p.set_defaults(func=_evaluate)


def _train(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads

    config = load_config(args.config)
    set_threads(args.threads or config["threads"]["train"])
    from dozerlab.learn.jobs import train_job

    result = train_job(args.model, args.train, config, args.out, device=args.device)
    print(
        f"{args.model}: best validation loss {min(result.val_loss):.4g} at epoch {result.best_epoch} "
        f"({result.samples['train']} training samples, {result.seconds:.1f} s) -> {args.out}"
    )
    return 0


def _validate(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads

    set_threads(args.threads)
    from dozerlab.learn.jobs import validate_job

    result = validate_job(
        args.model,
        args.interpolation,
        args.extrapolation,
        args.out,
        args.plots,
        load_config(args.config),
    )
    print(result["summary"])
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from dozerlab.runtime import set_threads

    set_threads(args.threads)
    from dozerlab.learn.jobs import evaluate_job

    result = evaluate_job(args.model, args.stores)
    cols = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
    print(f"{'store':40s} " + " ".join(f"{c:>16s}" for c in cols) + "   (rel. RMSE % / R²)")
    for label, m in [(p["name"], p["metrics"]) for p in result["points"]] + [
        ("overall", result["overall"])
    ]:
        print(
            f"{label[:40]:40s} "
            + " ".join(f"{100 * m[c]['rel_rmse']:8.1f}/{m[c]['r2']:7.3f}" for c in cols)
        )
    return 0
