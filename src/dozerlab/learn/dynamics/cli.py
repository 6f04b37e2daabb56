"""``dozerlab train-dynamics`` and ``validate-dynamics``: the field-evolution commands."""

from __future__ import annotations

import argparse

from dozerlab.learn.cli import add_held_out

MODELS = ["persistence", "ridge", "unet"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train-dynamics", help="train one field-evolution model on field stores")
    p.add_argument("--model", required=True, choices=MODELS, help="model name")
    p.add_argument(
        "--train", required=True, nargs="+", metavar="F.zarr", help="training field stores"
    )
    p.add_argument(
        "--config", default=None, help="YAML file or inline JSON (default: all defaults)"
    )
    p.add_argument("--out", required=True, help="model directory to write (results/dynamics/NAME)")
    p.add_argument(
        "--threads", type=int, default=None, help="thread budget (default: config threads.dynamics)"
    )
    p.add_argument(
        "--device", default=None, help="torch device (default: cuda if present, else cpu)"
    )
    p.set_defaults(func=_train)

    p = sub.add_parser(
        "validate-dynamics",
        help="one-step and rollout errors of an evolution model on held-out points",
    )
    p.add_argument("--model", required=True, help="model directory (results/dynamics/NAME)")
    add_held_out(p)
    p.add_argument("--out", required=True, help="JSON to write (results/dynamics/NAME.json)")
    p.add_argument(
        "--plots", default=None, help="plot folder (default: plots/NAME beside the JSON)"
    )
    p.add_argument(
        "--config", default=None, help="YAML file or inline JSON (dynamics, mlflow sections)"
    )
    p.add_argument("--threads", type=int, default=1, help="thread budget")
    p.set_defaults(func=_validate)


def _train(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads

    config = load_config(args.config)
    set_threads(args.threads or config["threads"]["dynamics"])
    from dozerlab.learn.dynamics.jobs import train_dynamics_job

    r = train_dynamics_job(args.model, args.train, config, args.out, device=args.device)
    print(
        f"dynamics {args.model}: validation rollout loss {min(r.val_loss):.4g} at epoch {r.best_epoch} "
        f"({r.samples['train']} training windows, {r.seconds:.1f} s) -> {args.out}"
    )
    return 0


def _validate(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads

    config = load_config(args.config)
    set_threads(args.threads)
    from dozerlab.learn.dynamics.jobs import validate_dynamics_job

    result = validate_dynamics_job(
        args.model, args.interpolation, args.extrapolation, args.out, config, args.plots
    )
    print(result["summary"])
    return 0
