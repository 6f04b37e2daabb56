"""The loop's force model by its rows of history and penalty, on a workflow's results: fitted
as rule ``train_loop_force`` fits it, then read on the held-out points' reduced runs.

    python benchmarks/loop_force.py --results results [--config config/config.yaml] \\
        [--dynamics ridge unet persistence] [--histories 1 2 3] [--alphas 1.0] [--oracle] \\
        [--kinds linear] [--with-ndem] [--threads 1]

For each dynamics model under ``results/reduced/{model}/``, each force model kind (``--kinds``,
``linear`` as the workflow's default ``reduced.force_model``) and each history and ridge alpha,
the force model is fitted to that model's reduced runs of the training points, paired
row by row with NDEM's force (``learn.jobs`` with loop fields), and then reads the fields of
its reduced runs of the held-out points. The grains never read the force, so these are the
forces the loop would have written (from the third row on, so that every history up to 3 is
read on the same rows). Prints, per held-out point, the pushing force's error low-passed over
0.1 s over the twin's (NDEM against NDEM from a bed moved 1 µm; the
comparison's ``force_lp_rel_rmse_skill``) and the error of its mean over the pass, and the
validation loss of the fit (normalised MSE on the early-stopping blocks of the training runs).

``--oracle`` also fits each setting with the held-out runs among its training runs: how well
the loop's fields determine the force when the model has seen the runs it is read on.
``--dynamics ndem`` fits and reads NDEM's own fields instead of a loop's: the force the fields
of NDEM's runs determine, which a loop's fields can at best match. ``--with-ndem`` also fits
each setting on NDEM's own fields of the training points beside the loop's (twice the runs,
the same targets): whether a model that has seen both generalises better to the loop's fields
at the held-out points.
"""

from __future__ import annotations

import argparse
import copy
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.learn.data import StoreData, load_store, with_loop_fields
from dozerlab.learn.pyfunc import predict_arrays
from dozerlab.learn.train import train_model
from dozerlab.reduce.compare import force_lp_rel_rmse
from dozerlab.runtime import set_threads

#: ``--dynamics`` name of no loop: NDEM's own fields, fitted and read as the loops' are.
NDEM = "ndem"
#: The most rows of history compared (``--histories`` up to it).
HISTORY_ROWS = 3


def paired(results: Path, model: str, points: list[P.SweepPoint]) -> list[StoreData]:
    """NDEM's stores of ``points`` with the fields of ``model``'s reduced runs of them (``ndem``:
    NDEM's own fields)."""
    if model == NDEM:
        return [load_store(P.field_path(results, p)) for p in points]
    return [
        with_loop_fields(
            load_store(P.field_path(results, p)), load_store(P.reduced_path(results, model, p))
        )
        for p in points
    ]


def figures(
    module: Any, results: Path, model: str, held_out: list[P.SweepPoint]
) -> list[tuple[float, float]]:
    """(low-passed force error over the twin's, mean force error) at each held-out point."""
    out = []
    for p in held_out:
        loop = load_store(
            P.field_path(results, p) if model == NDEM else P.reduced_path(results, model, p)
        )
        ndem, twin = load_store(P.field_path(results, p)), load_store(P.twin_path(results, p))
        arrays = {
            "velocity": loop.velocity,
            "density": loop.density,
            "blade_velocity": loop.blade_velocity,
        }
        force = predict_arrays(module, arrays)[:, :3].astype(np.float64)
        # rows before the first window of HISTORY_ROWS rows take NDEM's force (the loop's
        # warm-up row does): every history is read on the same rows, and a window padded with
        # copies of the first row, whose changes are all zero, is not read
        force[: HISTORY_ROWS - 1] = ndem.target[: HISTORY_ROWS - 1, :3]
        rows = slice(HISTORY_ROWS - 1, None)
        err = force_lp_rel_rmse(force, ndem.target[:, :3], ndem.row_dt, rows)
        floor = force_lp_rel_rmse(twin.target[:, :3], ndem.target[:, :3], ndem.row_dt, rows)
        mean = abs(force[rows, 0].mean() / ndem.target[rows, 0].mean() - 1.0)
        out.append((err / floor, mean))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--dynamics", nargs="+", default=["ridge", "unet", "persistence"])
    ap.add_argument("--histories", nargs="+", type=int, default=[1, 2, 3])
    ap.add_argument("--alphas", nargs="+", type=float, default=None)
    ap.add_argument("--oracle", action="store_true")
    ap.add_argument("--kinds", nargs="+", default=["linear"], help="force model kinds")
    ap.add_argument("--with-ndem", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    if not all(1 <= h <= HISTORY_ROWS for h in args.histories):
        ap.error(f"--histories: each from 1 to {HISTORY_ROWS}")
    set_threads(args.threads)
    cfg = load_config(args.config)
    points = P.sweep_points(cfg)
    train, held_out = P.by_role(points, "train"), [p for p in points if p.role != "train"]
    alphas = args.alphas or [cfg["learn"]["ridge_alpha"]]
    print("held-out points: " + ", ".join(f"{p.scenario} {p.speed}/{p.depth}" for p in held_out))
    print("per point: low-passed force error / the twin's, mean force error")
    ndem = paired(args.results, NDEM, train) if args.with_ndem else []
    for model in args.dynamics:
        stores = paired(args.results, model, train)
        fits = [("", stores)]
        if args.oracle:
            fits.append((" oracle", stores + paired(args.results, model, held_out)))
        if ndem and model != NDEM:
            # the loop's runs unlabelled: each point's two field sources are two runs of it
            fits.append((" with NDEM's fields", [replace(s, point={}) for s in stores] + ndem))
        for kind in args.kinds:
            for history in args.histories:
                # the ridge penalty is the linear model's alone
                for alpha in alphas if kind == "linear" else alphas[:1]:
                    c = copy.deepcopy(cfg)
                    c["learn"].update(history=history, ridge_alpha=alpha)
                    for label, fit_on in fits:
                        result = train_model(kind, fit_on, c)
                        found = figures(result.model, args.results, model, held_out)
                        print(
                            f"{model} {kind} history {history}"
                            + (f" alpha {alpha:g}" if kind == "linear" else "")
                            + f"{label}: "
                            + "  ".join(f"{s:.2f}/{m * 100:.1f}%" for s, m in found)
                            + f"  | mean {np.mean([s for s, _ in found]):.2f}"
                            + f", validation loss {min(result.val_loss):.3f}",
                            flush=True,
                        )


if __name__ == "__main__":
    main()
