"""The reduced loop under settings side by side, on a sweep's held-out points.

    python benchmarks/reduce_settings.py --results results [--config config/config.yaml] \\
        [--dynamics ridge] [--threads 1] \\
        "one row:reduced.step_rows=1,reduced.projection.iterations=48" "default:"

Each argument is a variant, ``NAME:KEY=VALUE,...`` (dotted config keys, values as YAML), laid
over ``--config`` and validated like it. For each variant and each held-out point of the config
(interpolation, extrapolation, transfer), runs the reduced loop as rule ``reduce_points`` does
(``reduce_run``, one thread, the heap frozen once the models are loaded) with the dynamics model
of ``--results`` (``replay``: the point's NDEM fields) and the force model rule ``reduce`` gives
it (``sweep.reduce_force_model_path``: with ``reduced.force_fields`` loop its loop force model,
replay's ``results/models/{force_model}``), into a temporary folder, and
compares it with the point's NDEM run and its twin (``compare_point``). Prints per point the
loop's wall time, its speed-up over the stored NDEM run's ``wall_time_s`` per simulated second,
ms a row projecting, sweeps and contact tests a step, grains moved a step, the largest overlap,
and the smoothed-surface and low-passed force skills; then per variant the loops' sum and the skills.
The variants run alternately point by point, so machine noise falls on all of them alike. Reads
``--results`` only. The force model was fitted to the loop fields of the workflow's settings:
under other settings its force skill is a lower bound of what retraining would give.

Each loop's line also gives, in front of the blade (the force models' part of the volume), the
mass over NDEM's at the pass's last row (above 1: more grains there than NDEM's) and the
density error column by column: the RMS over rows, x and z of the density summed across y
(what the linear force model reads), over NDEM's RMS.

``--points training`` runs the training points instead: they have no twin, so the figures are
the smoothed-surface accuracy and the low-passed force error against the point's NDEM run, and
choosing a setting on them leaves the held-out points unseen. ``--jitter-seeds`` runs each loop
from the bed and from copies with every grain moved by 1 µm (a seed a copy, 0 the bed itself):
the loop's own draw-to-draw spread; the summary gives each point's mean over them.
"""

from __future__ import annotations

import argparse
import copy
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.runtime import freeze_heap, set_threads


def _top_level(items: str) -> list[str]:
    """``items`` split at the commas outside brackets and braces."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(items):
        depth += (ch in "[{") - (ch in "]}")
        if ch == "," and depth == 0:
            parts.append(items[start:i])
            start = i + 1
    return [*parts, items[start:]]


def variant(text: str, base: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """``NAME:KEY=VALUE,...`` → (name, ``base`` with those fields set, validated). A comma
    inside a YAML list or mapping belongs to the value: ``dynamics.ridge_z_bands=[1,4]``."""
    name, _, items = text.partition(":")
    cfg = copy.deepcopy(base)
    for item in filter(None, _top_level(items)):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"variant {text!r}: {item!r} is not KEY=VALUE")
        node = cfg
        *path, last = key.split(".")
        for part in path:
            node = node.setdefault(part, {})
        node[last] = yaml.safe_load(value)
    return name or text, load_config(cfg)


def front_density(store: Any) -> np.ndarray:
    """The density (rows, x, y, z) kg/m³ over the store's blade part (the bins in front of the blade)."""
    x0, y0, x1, y1 = store.attrs["blade_part"]
    return np.asarray(store["density"].values[:, x0:x1, y0:y1], np.float64)


def front_figures(run: Any, ndem: Any) -> tuple[float, float]:
    """The run's mass in front of the blade over NDEM's at the last row, and its (x, z) column
    density error over NDEM's RMS (the module doc)."""
    a, b = front_density(ndem), front_density(run)
    n = min(len(a), len(b))
    cols_a, cols_b = a[:n].sum(axis=2), b[:n].sum(axis=2)
    error = np.sqrt(np.mean((cols_b - cols_a) ** 2) / np.mean(cols_a**2))
    return float(b[n - 1].sum() / a[n - 1].sum()), float(error)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("variants", nargs="+", help="NAME:KEY=VALUE,... (see the module doc)")
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--dynamics", default="ridge")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--points", choices=("held-out", "training"), default="held-out")
    ap.add_argument("--jitter-seeds", type=int, nargs="+", default=[0], metavar="SEED")
    args = ap.parse_args()
    os.environ.setdefault("DOZERLAB_MLFLOW", "0")
    set_threads(args.threads)
    from dozerlab.fields.store import open_store
    from dozerlab.reduce.compare import compare_point
    from dozerlab.reduce.models import ForcePredictor, load_field_model
    from dozerlab.reduce.run import reduce_run
    from dozerlab.scenarios.bed import Bed

    base = load_config(args.config)
    variants = [variant(text, base) for text in args.variants]
    res = args.results
    training = args.points == "training"
    points = [p for p in P.sweep_points(base) if (p.role == "train") == training]
    # held-out points are scored against NDEM's twin (skills), training points against NDEM
    surface_key, force_key = (
        ("surface_accuracy", "force_lp_rel_rmse")
        if training
        else ("surface_accuracy_skill", "force_lp_rel_rmse_skill")
    )
    force = ForcePredictor(P.reduce_force_model_path(res, base["reduced"], args.dynamics))
    figures: dict[str, list[list[tuple[float, ...]]]] = {n: [] for n, _ in variants}
    with tempfile.TemporaryDirectory() as tmp:
        for pt in points:
            model = load_field_model(
                "replay"
                if args.dynamics == "replay"
                else P.dynamics_model_path(res, args.dynamics),
                tuple(base["sampling"]["bins"]),
                P.field_path(res, pt),
            )
            freeze_heap()  # as the reduce job does: no full collection walks the models mid-loop
            beds = {}
            for seed in args.jitter_seeds:
                beds[seed] = P.bed_path(res, pt.scenario)
                if seed:
                    beds[seed] = Path(tmp) / f"bed-{seed}.npz"
                    Bed.load(P.bed_path(res, pt.scenario)).jittered(1e-6, seed).save(beds[seed])
            for name, cfg in variants:
                draws = []
                for seed, bed in beds.items():
                    store, state = Path(tmp) / "run.zarr", Path(tmp) / "run.npz"
                    r = reduce_run(
                        bed,
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
                        twin=None
                        if training
                        else (P.twin_path(res, pt, "zarr"), P.twin_path(res, pt, "npz")),
                    )
                    surface, force_fig = m[surface_key], m[force_key]
                    speedup = m.get("loop_speedup") or float("nan")
                    front, columns = front_figures(
                        open_store(store), open_store(P.field_path(res, pt))
                    )
                    draws.append((r["wall_time_s"], speedup, surface, force_fig, front, columns))
                    print(
                        f"{name:>12} {pt.scenario} {pt.speed}/{pt.depth}"
                        f"{f' (bed jittered, seed {seed})' if seed else ''}: loop "
                        f"{r['wall_time_s']:.2f} s ({speedup:.1f}x NDEM), projection "
                        f"{r['ms_projection']:.2f} ms a row, {r['projection_sweeps_mean']:.1f} "
                        f"sweeps, {r.get('projection_tests_mean', np.nan) / 1e3:.0f}k contact tests "
                        f"and {r['active_grains_mean']:.0f} grains moved a step, largest overlap "
                        f"{r['max_overlap']:.3f} r, {surface_key.replace('_', ' ')} {surface:.3f}, "
                        f"{force_key.replace('_', ' ')} {force_fig:.2f}, front mass {front:.3f}x NDEM's, "
                        f"column density error {columns:.3f}",
                        flush=True,
                    )
                figures[name].append(draws)
    for name, rows in figures.items():
        a = np.array(rows)  # (points, draws, 6)
        mean = a.mean(axis=1)
        spread = (
            f", spread (sd over the draws) {np.round(a[:, :, 2].std(axis=1, ddof=1), 3).tolist()}"
            if a.shape[1] > 1
            else ""
        )
        print(
            f"{name}: loops {a[:, :, 0].sum():.2f} s in all, speed-up "
            f"{np.round(mean[:, 1], 1).tolist()}, {surface_key.replace('_', ' ')} "
            f"{np.round(mean[:, 2], 3).tolist()} (mean {mean[:, 2].mean():.3f}){spread}, "
            f"{force_key.replace('_', ' ')} {np.round(mean[:, 3], 3).tolist()} (mean "
            f"{mean[:, 3].mean():.3f}), front mass over NDEM's {np.round(mean[:, 4], 3).tolist()}, "
            f"column density error {np.round(mean[:, 5], 3).tolist()}"
        )


if __name__ == "__main__":
    main()
