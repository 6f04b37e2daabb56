"""The adaptive design's learning curve on the stores of an existing sweep, without new runs.

Replays config/adaptive.yaml's rounds (their picks read from the stores of a finished default
sweep, so the candidates must be runs there: the grid's lattice) and computes the learning curve
of the adaptive design, the grid and random designs of the same sizes on the held-out points,
and (where the results hold the held-out points' replay runs) the reduced simulation's
low-passed pushing-force error of each training set's force model in the replay loops:

    python benchmarks/adaptive_curve.py --results /tmp/v1/results --out /tmp/curve.csv
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from dozerlab.adaptive import design
from dozerlab.adaptive.curve import LOOP_COLUMNS, mean_by_size, write_curve
from dozerlab.adaptive.jobs import comparison_designs, learning_curve, read_run
from dozerlab.config import load_config, read_yaml
from dozerlab.sweep import field_path


def merged(*files: str) -> dict:
    """Config files laid over each other as Snakemake does (mappings merged key by key)."""

    def merge(a: dict, b: dict) -> dict:
        for k, v in b.items():
            a[k] = merge(a[k], v) if isinstance(v, dict) and isinstance(a.get(k), dict) else v
        return a

    out: dict = {}
    for f in files:
        out = merge(out, read_yaml(f))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--results", required=True, help="results folder of a finished default sweep")
    ap.add_argument(
        "--configfile", nargs="+", default=["config/config.yaml", "config/adaptive.yaml"]
    )
    ap.add_argument("--out", required=True, help="learning-curve CSV to write")
    args = ap.parse_args()
    cfg = load_config(merged(*args.configfile))
    rounds = [design.round_zero(cfg)]
    runs = {}
    for r in range(1, cfg["sweep"]["adaptive"]["rounds"] + 1):
        for s in rounds[-1]:
            p, y, n = read_run(field_path(args.results, s.point))
            runs[p] = (y, n)
        taken = [s.point for x in rounds for s in x]
        rounds.append(design.next_round(cfg, r, taken, runs))
    for r, rows in enumerate(rounds):
        for s in rows:
            print(f"round {r}: {s.point.scenario} {s.point.name} score {s.score:.3g} ({s.why})")
    t0 = time.perf_counter()
    rows = learning_curve(
        cfg, comparison_designs(cfg, [[s.point for s in x] for x in rounds]), args.results
    )
    write_curve(Path(args.out), rows)
    print(f"learning curve: {len(rows)} rows in {time.perf_counter() - t0:.0f} s -> {args.out}")
    for column in ("heldout_force_rel_rmse", *LOOP_COLUMNS):
        # errors as percentages, the skill (an error over the twin's) as a ratio
        scale = 1 if column.endswith("_skill") else 100
        print(column, "" if scale == 1 else "(%)")
        for name in ("adaptive", "grid", "random"):
            by_size = mean_by_size(rows, name, column)
            print(" ", name, {n: round(scale * e, 3) for n, e in by_size.items()})
            if name == "random":
                spread = {
                    n: (round(scale * min(v), 3), round(scale * max(v), 3))
                    for n in by_size
                    if (v := [r[column] for r in rows if r["design"] == name and r["runs"] == n])
                }
                print("  random min-max", spread)


if __name__ == "__main__":
    main()
