"""Commands of the fields layer: ``simulate``, ``plot-fields``, ``import-legacy``, ``export-legacy``."""

from __future__ import annotations

import argparse

from dozerlab.cliargs import (
    add_command,
    add_config,
    add_labels,
    add_run_inputs,
    add_threads,
    configure,
    labels,
    schema_value,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "simulate",
        "run the grain simulation (NDEM) along a blade trajectory and record the fields",
        "python -m dozerlab simulate --config config/quick.yaml --bed results/beds/hill.npz \\\n"
        "      --trajectory results/trajectories/hill/speed~1.0_depth~0.04.csv \\\n"
        "      --out results/fields/hill/speed~1.0_depth~0.04.zarr \\\n"
        "      --state results/states/hill/speed~1.0_depth~0.04.npz",
    )
    add_run_inputs(p)
    add_config(p)
    p.add_argument("--out", required=True, help="field store to write (.zarr)")
    p.add_argument(
        "--state", default=None, help="write the final particle state here (.npz, a bed file)"
    )
    add_threads(p)
    p.add_argument(
        "--vtk-dir",
        default=None,
        help="write particle VTK snapshots here every sampling.vtk_every steps",
    )
    p.add_argument(
        "--plots", default=None, help="write field-slice, force and GIF plots of the run here"
    )
    p.add_argument(
        "--jitter",
        type=schema_value(("reduced", "twin", "jitter_m")),
        default=None,
        help="a twin run: move every grain of the bed this far (m) in a seeded random direction "
        "first (the bounds of reduced.twin.jitter_m)",
    )
    p.add_argument(
        "--jitter-seed",
        type=schema_value(("reduced", "twin", "seed"), int),
        default=None,
        help="seed of the jitter's directions (default: reduced.twin.seed)",
    )
    add_labels(p)
    p.set_defaults(func=_simulate)

    p = add_command(
        sub,
        "plot-fields",
        "draw field slices, the force plot and an animation of a field store",
        "python -m dozerlab plot-fields results/fields/hill/speed~1.0_depth~0.04.zarr \\\n"
        "      --out results/plots/hill/speed~1.0_depth~0.04",
    )
    p.add_argument("store", help="field store (.zarr)")
    p.add_argument("--out", required=True, help="directory for the PNGs and the GIF")
    p.add_argument(
        "--steps",
        type=int,
        nargs="+",
        default=None,
        help="time indices to slice (default: 4 spread)",
    )
    p.add_argument("--frames", type=int, default=60, help="frames of the GIF (default 60)")
    p.add_argument("--no-animation", action="store_true", help="skip the GIF")
    p.set_defaults(func=_plot)

    p = add_command(
        sub,
        "import-legacy",
        "convert the thesis's binary field file to a field store",
        "python -m dozerlab import-legacy speed~1.0_depth~0.04.bin \\\n"
        "      results/fields/legacy/speed~1.0_depth~0.04.zarr",
    )
    p.add_argument("file", help="legacy binary file")
    p.add_argument("out", help="field store to write (.zarr)")
    p.add_argument(
        "--lower",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="sampling volume's minimum corner relative to the tip in m (default: 0, -width/2, 0)",
    )
    p.set_defaults(func=_import)

    p = add_command(
        sub,
        "export-legacy",
        "write a field store in the thesis's binary format",
        "python -m dozerlab export-legacy results/fields/hill/speed~1.0_depth~0.04.zarr \\\n"
        "      speed~1.0_depth~0.04.bin",
    )
    p.add_argument("store", help="field store (.zarr)")
    p.add_argument("out", help="binary file to write (a new one unless --overwrite)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing legacy binary file at OUT: the format has no room for a mark "
        "of ours, so without this flag any existing file is refused",
    )
    p.set_defaults(func=_export)


def _simulate(args: argparse.Namespace) -> int:
    if args.jitter_seed is not None and args.jitter is None:
        raise ValueError("--jitter-seed needs --jitter (the twin's jitter in m)")
    config = configure(args)
    from dozerlab.fields.jobs import Jitter, simulate

    jitter = None
    if args.jitter is not None:
        seed = args.jitter_seed
        jitter = Jitter(args.jitter, config["reduced"]["twin"]["seed"] if seed is None else seed)
    outputs = {"vtk_dir": args.vtk_dir, "plots_dir": args.plots, "state_out": args.state}
    simulate(args.bed, args.trajectory, config, args.out, **outputs, **labels(args), jitter=jitter)
    return 0


def _plot(args: argparse.Namespace) -> int:
    from dozerlab.fields.plots import FIELD_PLOTS, plot_run
    from dozerlab.fields.store import open_store
    from dozerlab.runtime import job_outputs

    with job_outputs(("--out", args.out, FIELD_PLOTS)):
        paths = plot_run(
            open_store(args.store),
            args.out,
            steps=args.steps,
            animation=not args.no_animation,
            frames=args.frames,
        )
    for path in paths:
        print(path)
    return 0


def _import(args: argparse.Namespace) -> int:
    from dozerlab.fields.legacy import import_legacy

    print(import_legacy(args.file, args.out, lower=args.lower))
    return 0


def _export(args: argparse.Namespace) -> int:
    from dozerlab.fields.legacy import export_legacy

    print(export_legacy(args.store, args.out, overwrite=args.overwrite))
    return 0
