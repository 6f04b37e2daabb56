"""``dozerlab train``, ``validate`` and ``evaluate``: the learning commands, and the parsers and
handlers of training and validation that the field-evolution commands share."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from dozerlab.cliargs import add_command, add_config, add_threads, configure, job
from dozerlab.learn.names import MODEL_NAMES


def add_held_out(p: argparse.ArgumentParser) -> None:
    """The held-out stores' options of a validation command."""
    for name, what in (
        ("interpolation", "held-out stores inside the training ranges"),
        ("extrapolation", "held-out stores outside them"),
        ("transfer", "held-out stores on terrain of no training point (unseen terrain)"),
    ):
        p.add_argument(f"--{name}", nargs="*", default=[], metavar="F.zarr", help=what)


def add_training(
    sub: argparse._SubParsersAction,
    name: str,
    help: str,
    example: str,
    *,
    run: str,
    models: Sequence[str] = MODEL_NAMES,
    results: str = "models",
    threads_key: str = "train",
    report: tuple[str, str, str] = ("", "best validation loss", "samples"),
    loop_fields: bool = False,
) -> None:
    """A training command (``help`` and ``example``: :func:`dozerlab.cliargs.add_command`):
    ``--model`` (one of ``models``) trained on ``--train`` stores into
    ``--out`` (``results/{results}/NAME``) by the job ``run`` (``module:function``); ``report``
    (prefix, loss, samples) words the line it prints; ``loop_fields`` adds ``--loop-fields``.
    The defaults are those of the force models' ``train``."""
    p = add_command(sub, name, help, example)
    p.add_argument("--model", required=True, choices=models, help="model name")
    p.add_argument(
        "--train", required=True, nargs="+", metavar="F.zarr", help="training field stores"
    )
    add_config(p)
    p.add_argument(
        "--out", required=True, help=f"model directory to write (results/{results}/NAME)"
    )
    add_threads(p, None, f"thread budget (default: config threads.{threads_key})")
    p.add_argument(
        "--device", default=None, help="torch device (default: cuda if present, else cpu)"
    )
    if loop_fields:
        p.add_argument(
            "--loop-fields",
            nargs="+",
            default=None,
            metavar="F.zarr",
            help="the reduced loop's runs of the --train points, in the same order: their "
            "velocity and density replace NDEM's (the force model of the reduced loop)",
        )
    p.set_defaults(func=_train, threads_key=threads_key, run=run, report=report)


def add_validation(
    sub: argparse._SubParsersAction,
    name: str,
    help: str,
    example: str,
    *,
    run: str,
    models: str = "models",
    results: str = "validation",
    plots: str = "the JSON path without .json",
    sections: str = "mlflow section",
) -> None:
    """A validation command (``help`` and ``example``: :func:`dozerlab.cliargs.add_command`):
    the ``--model`` directory (``results/{models}/NAME``) on held-out
    stores, metrics to ``--out`` (``results/{results}/NAME.json``) and plots to ``--plots``
    (default: ``plots``) by the job ``run`` (``module:function``); the config's ``sections`` are
    read. The defaults are those of the force models' ``validate``."""
    p = add_command(sub, name, help, example)
    p.add_argument("--model", required=True, help=f"model directory (results/{models}/NAME)")
    add_held_out(p)
    p.add_argument("--out", required=True, help=f"JSON to write (results/{results}/NAME.json)")
    p.add_argument("--plots", default=None, help=f"plot folder (default: {plots})")
    add_config(p, f"YAML file or inline JSON ({sections})")
    add_threads(p, help="thread budget")
    p.set_defaults(func=_validate, run=run)


def register(sub: argparse._SubParsersAction) -> None:
    add_training(
        sub,
        "train",
        "train one force/torque model on field stores",
        "python -m dozerlab train --model linear --config config/quick.yaml \\\n"
        "      --train results/fields/hill/speed~1.0_depth~0.04.zarr \\\n"
        "              results/fields/hill/speed~1.5_depth~0.04.zarr \\\n"
        "      --out results/models/linear",
        run="dozerlab.learn.jobs:train_job",
        loop_fields=True,
    )
    add_validation(
        sub,
        "validate",
        "measure a force model on held-out sweep points: metrics (JSON) and plots",
        "python -m dozerlab validate --model results/models/linear --config config/quick.yaml \\\n"
        "      --interpolation results/fields/hill/speed~1.25_depth~0.06.zarr \\\n"
        "      --extrapolation results/fields/hill/speed~0.75_depth~0.08.zarr \\\n"
        "      --out results/validation/linear.json",
        run="dozerlab.learn.jobs:validate_job",
    )

    p = add_command(
        sub,
        "evaluate",
        "print a force model's metrics on field stores",
        "python -m dozerlab evaluate --model results/models/linear \\\n"
        "      results/fields/hill/speed~1.25_depth~0.06.zarr",
    )
    p.add_argument("--model", required=True, help="model directory")
    p.add_argument("stores", nargs="+", metavar="STORE", help="field stores")
    add_threads(p, help="thread budget")
    p.set_defaults(func=_evaluate)


def _train(args: argparse.Namespace) -> int:
    config = configure(args, args.threads_key)
    extra = {"loop_fields": args.loop_fields} if getattr(args, "loop_fields", None) else {}
    result = job(args.run)(args.model, args.train, config, args.out, device=args.device, **extra)
    prefix, loss, samples = args.report
    best = (
        f"epoch {result.best_epoch + 1}"
        if result.penalty is None
        else f"penalty {result.penalty:g}"
    )
    print(
        f"{prefix}{args.model}: {loss} {min(result.val_loss):.4g} at {best} "
        f"({result.samples['train']} training {samples}, {result.seconds:.1f} s) -> {args.out}"
    )
    return 0


def _validate(args: argparse.Namespace) -> int:
    config = configure(args)
    result = job(args.run)(
        args.model,
        args.interpolation,
        args.extrapolation,
        args.out,
        plots_dir=args.plots,
        config=config,
        transfer=args.transfer,
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
