"""Where the reduced loop's overlaps are: every pair of the whole bed after every step, against
the step's own largest-overlap statistic, on one sweep point.

    python benchmarks/reduce_overlaps.py --results results --scenario hill --speed 0.875 \\
        --depth 0.045 [--config config/config.yaml] [--dynamics replay] [--bound 0.1]

Runs the reduced loop (``reduce_run``, the config's force model) on the point's bed, trajectory
and NDEM store under ``--results`` (read only; outputs in a temporary folder) and, after each
step, searches the whole bed for overlapping pairs. Prints the loop's largest overlap, the whole
bed's, the steps with a pair above ``--bound`` radii, and those pairs split by which of their
grains the step moved (both, one, none: an overlap left from an earlier step), then the final
state's largest overlap. The whole-bed search is outside the loop's phases: its ms per row are
the loop's own.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.runtime import set_threads
from reduce_loop import point_parser  # the sibling benchmark (benchmarks/ is on sys.path)


def main() -> None:
    ap = point_parser(__doc__)
    ap.add_argument("--dynamics", default="replay")
    ap.add_argument("--bound", type=float, default=0.1, help="overlap counted, over the radius")
    args = ap.parse_args()
    os.environ["DOZERLAB_MLFLOW"] = "0"
    set_threads(1)
    from dozerlab.reduce.compare import largest_overlap
    from dozerlab.reduce.models import ForcePredictor, load_field_model
    from dozerlab.reduce.projection import candidate_pairs
    from dozerlab.reduce.run import reduce_run
    from dozerlab.reduce.simulation import ReducedState

    cfg = load_config(args.config)
    point = P.SweepPoint(args.scenario, args.speed, args.depth)
    res = Path(args.results)
    rows: list[tuple[float, float, int, int, int, int]] = []
    step = ReducedState.step

    def traced(state: ReducedState, *a: object, **k: object) -> object:
        before = state.x.copy()
        stats = step(state, *a, **k)
        pi, pj = candidate_pairs(state.x, state.r, 0.0)
        dist = np.linalg.norm(state.x[pi] - state.x[pj], axis=1)
        gap = (state.r[pi] + state.r[pj] - dist) / np.minimum(state.r[pi], state.r[pj])
        moved = np.any(state.x != before, axis=1)
        bad = gap > args.bound
        both = int(np.sum(bad & moved[pi] & moved[pj]))
        none = int(np.sum(bad & ~moved[pi] & ~moved[pj]))
        worst = float(gap.max(initial=0.0))
        rows.append(
            (stats.max_overlap, worst, int(bad.sum()), both, int(bad.sum()) - both - none, none)
        )
        return stats

    ReducedState.step = traced
    source = (
        args.dynamics if args.dynamics == "replay" else P.dynamics_model_path(res, args.dynamics)
    )
    fm = load_field_model(source, tuple(cfg["sampling"]["bins"]), P.field_path(res, point))
    force = ForcePredictor(P.model_path(res, cfg["reduced"]["force_model"]))
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        r = reduce_run(
            P.bed_path(res, point.scenario),
            P.trajectory_path(res, point),
            cfg,
            fm,
            force,
            t / "reduced.zarr",
            t / "reduced.npz",
            scenario=point.scenario,
            speed=point.speed,
            depth=point.depth,
        )
        from dozerlab.scenarios.bed import Bed

        final = Bed.load(t / "reduced.npz")
        final_overlap = largest_overlap(final.positions, final.radii)
    a = np.array(rows)
    print(f"{point.scenario} {point.name}, {args.dynamics}: {len(a)} steps")
    print(
        f"largest overlap over the radius: the loop's statistic {a[:, 0].max():.3f}, the whole "
        f"bed after a step {a[:, 1].max():.3f}, the final state {final_overlap:.3f}"
    )
    print(
        f"steps with a pair above {args.bound} r: {int((a[:, 2] > 0).sum())} (at most "
        f"{int(a[:, 2].max())} pairs); those pairs over the steps: both grains moved by the step "
        f"{int(a[:, 3].sum())}, one {int(a[:, 4].sum())}, none {int(a[:, 5].sum())}"
    )
    phases = ", ".join(f"{k[3:]} {v:.2f}" for k, v in r.items() if k.startswith("ms_"))
    print(f"ms per row: {phases}; projection sweeps per step {r['projection_sweeps_mean']:.1f}")


if __name__ == "__main__":
    main()
