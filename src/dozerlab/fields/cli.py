"""Commands of the fields layer: ``simulate``, ``plot-fields``, ``import-legacy``, ``export-legacy``."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="run NDEM along a blade trajectory and record the fields")
    p.add_argument("--bed", required=True, help="settled bed (.npz from `dozerlab bed`)")
    p.add_argument(
        "--trajectory", required=True, help="blade trajectory (.csv from `dozerlab trajectory`)"
    )
    p.add_argument(
        "--config", default=None, help="YAML file or inline JSON (default: all defaults)"
    )
    p.add_argument("--out", required=True, help="field store to write (.zarr)")
    p.add_argument(
        "--state", default=None, help="write the final particle state here (.npz, a bed file)"
    )
    p.add_argument("--threads", type=int, default=1, help="numba threads (default 1)")
    p.add_argument(
        "--vtk-dir",
        default=None,
        help="write particle VTK snapshots here every sampling.vtk_every steps",
    )
    p.add_argument(
        "--plots", default=None, help="write field-slice, force and GIF plots of the run here"
    )
    p.add_argument("--scenario", default=None, help="label (default: the bed's scenario)")
    p.add_argument(
        "--speed", type=float, default=None, help="label in m/s (default: from the trajectory)"
    )
    p.add_argument(
        "--depth",
        type=float,
        default=None,
        help="label in m (default: none; the workflow passes its sweep point's)",
    )
    p.set_defaults(func=_simulate)

    p = sub.add_parser(
        "plot-fields", help="field slices, force plot and an animation of a field store"
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

    p = sub.add_parser(
        "import-legacy", help="convert the thesis's binary field file to a field store"
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

    p = sub.add_parser("export-legacy", help="write a field store in the thesis's binary format")
    p.add_argument("store", help="field store (.zarr)")
    p.add_argument("out", help="binary file to write")
    p.set_defaults(func=_export)


def _simulate(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads

    set_threads(args.threads)
    from dozerlab.fields.jobs import simulate

    simulate(
        args.bed,
        args.trajectory,
        load_config(args.config),
        args.out,
        scenario=args.scenario,
        speed=args.speed,
        depth=args.depth,
        vtk_dir=args.vtk_dir,
        plots_dir=args.plots,
        state_out=args.state,
    )
    return 0


def _plot(args: argparse.Namespace) -> int:
    from dozerlab.fields.plots import plot_run
    from dozerlab.fields.store import open_store

    for path in plot_run(
        open_store(args.store),
        args.out,
        steps=args.steps,
        animation=not args.no_animation,
        frames=args.frames,
    ):
        print(path)
    return 0


def _import(args: argparse.Namespace) -> int:
    from dozerlab.fields.legacy import import_legacy

    print(import_legacy(args.file, args.out, lower=args.lower))
    return 0


def _export(args: argparse.Namespace) -> int:
    from dozerlab.fields.legacy import export_legacy

    print(export_legacy(args.store, args.out))
    return 0
