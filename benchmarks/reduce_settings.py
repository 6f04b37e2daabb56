"""The reduced loop under settings side by side, on a sweep's held-out points.

    python benchmarks/reduce_settings.py --results results [--config config/config.yaml] \\
        [--dynamics ridge] [--threads 1] \\
        "one row:reduced.step_rows=1,reduced.projection.iterations=48" "default:"

Each argument is a variant, ``NAME:KEY=VALUE,...`` (dotted config keys, values as YAML), laid
over ``--config`` and validated like it. For each variant and each held-out point of the config
(interpolation, extrapolation, transfer), runs the reduced loop as rule ``reduce_points`` does
(``reduce_run``, one thread) with the dynamics model of ``--results`` (``replay``: the point's
NDEM fields) and its loop force model (``results/reduced/{model}/force_model``, or
``results/models/{force_model}`` where the model has none), into a temporary folder, and
compares it with the point's NDEM run and its twin (``compare_point``). Prints per point the
loop's wall time, its speed-up over the stored NDEM run's ``wall_time_s`` per simulated second,
ms a row projecting, sweeps and contact tests a step, grains moved a step, the largest overlap,
and the smoothed-surface and low-passed force skills; then per variant the loops' sum and the skills.
The variants run alternately point by point, so machine noise falls on all of them alike. Reads
``--results`` only. The force model was fitted to the loop fields of the workflow's settings:
under other settings its force skill is a lower bound of what retraining would give.
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
from dozerlab.runtime import set_threads


def _variant(text: str, base: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """``NAME:KEY=VALUE,...`` → (name, ``base`` with those fields set, validated)."""
    name, _, items = text.partition(":")
    cfg = copy.deepcopy(base)
    for item in filter(None, items.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"variant {text!r}: {item!r} is not KEY=VALUE")
        node = cfg
        *path, last = key.split(".")
        for part in path:
            node = node.setdefault(part, {})
        node[last] = yaml.safe_load(value)
    return name or text, load_config(cfg)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("variants", nargs="+", help="NAME:KEY=VALUE,... (see the module doc)")
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--dynamics", default="ridge")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    os.environ.setdefault("DOZERLAB_MLFLOW", "0")
    set_threads(args.threads)
    from dozerlab.reduce.compare import compare_point
    from dozerlab.reduce.models import ForcePredictor, load_field_model
    from dozerlab.reduce.run import reduce_run

    base = load_config(args.config)
    variants = [_variant(text, base) for text in args.variants]
    res = args.results
    points = [p for p in P.sweep_points(base) if p.role != "train"]
    loop_force = res / "reduced" / args.dynamics / "force_model"
    force = ForcePredictor(
        loop_force if loop_force.is_dir() else P.model_path(res, base["reduced"]["force_model"])
    )
    figures: dict[str, list[tuple[float, float, float, float]]] = {n: [] for n, _ in variants}
    with tempfile.TemporaryDirectory() as tmp:
        for pt in points:
            model = load_field_model(
                "replay"
                if args.dynamics == "replay"
                else P.dynamics_model_path(res, args.dynamics),
                tuple(base["sampling"]["bins"]),
                P.field_path(res, pt),
            )
            for name, cfg in variants:
                store, state = Path(tmp) / "run.zarr", Path(tmp) / "run.npz"
                r = reduce_run(
                    P.bed_path(res, pt.scenario),
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
                    twin=(P.twin_path(res, pt, "zarr"), P.twin_path(res, pt, "npz")),
                )
                surface, force_skill = m["surface_accuracy_skill"], m["force_lp_rel_rmse_skill"]
                speedup = m.get("loop_speedup") or float("nan")
                figures[name].append((r["wall_time_s"], speedup, surface, force_skill))
                print(
                    f"{name:>12} {pt.scenario} {pt.speed}/{pt.depth}: loop {r['wall_time_s']:.2f} s "
                    f"({speedup:.1f}x NDEM), projection {r['ms_projection']:.2f} ms a row, "
                    f"{r['projection_sweeps_mean']:.1f} sweeps, "
                    f"{r.get('projection_tests_mean', np.nan) / 1e3:.0f}k contact tests and "
                    f"{r['active_grains_mean']:.0f} "
                    f"grains moved a step, largest overlap {r['max_overlap']:.3f} r, "
                    f"surface skill {surface:.3f}, force skill {force_skill:.2f}",
                    flush=True,
                )
    for name, rows in figures.items():
        a = np.array(rows)
        print(
            f"{name}: loops {a[:, 0].sum():.2f} s in all, speed-up {np.round(a[:, 1], 1).tolist()}, "
            f"surface skill {np.round(a[:, 2], 3).tolist()} (mean {a[:, 2].mean():.3f}), "
            f"force skill {np.round(a[:, 3], 2).tolist()}"
        )


if __name__ == "__main__":
    main()
