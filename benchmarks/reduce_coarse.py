"""The reduced loop on beds of coarser grains: how much faster it runs, and the surface it leaves.

    python benchmarks/reduce_coarse.py --results results [--config config/config.yaml] \\
        [--radius-scales 1.26 1.5] [--repour] [--dynamics replay ridge] [--threads 1] \\
        [--workdir DIR]

Moving fewer, larger grains is one route to a faster loop: a bed of grains s times the radius
holds about s³ fewer of them. For each scale s the scenario's bed is built again from the config
with ``bed.radius`` times s, and each dynamics model's loop runs on it over every held-out
point's trajectory as rule ``reduce`` runs it: the models and force models the sweep under
``--results`` trained on NDEM's runs of the fine bed (replay reads NDEM's fine fields). The
final surface is scored against NDEM's fine run at the fine bed's smoothing (one fine grain
diameter), and as a skill over the twin's accuracy. Printed beside it, from the same process:
the same loop on the fine bed (the baseline: the sweep's reduced run), the loop's wall time and
per-phase ms a row, and how far the bed's own surface lies from the fine bed's before anything
moves (Σ|h − h_bed| over Σ|h_ndem − h_bed|, NDEM's change over the pass: a share of the pass's
change that the bed misses before any cut). With ``--repour`` the fine bed is poured again
with another seed (``seed`` + 1) as a control: what a bed of the same grains that is not NDEM's
costs a loop. Each loop's change of its own bed's surface added to the fine bed's is scored
too: an estimate of what a loop could reach that kept the fine grains at rest and moved coarse
ones, pessimistic by what it takes off the re-poured bed's loop.

The beds are built into ``--workdir`` (a temporary folder by default) and reused from there by
a later run with the same folder; nothing under ``--results`` is written.
"""

from __future__ import annotations

import argparse
import copy
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.reduce.compare import height_accuracy, smoothed_surface, surface_sigma
from dozerlab.runtime import set_threads
from dozerlab.scenarios.bed import Bed
from reduce_loop import run_loop  # the sibling benchmark (benchmarks/ is on sys.path)


def variant_bed(
    scenario: str, cfg: dict[str, Any], workdir: Path, name: str, *, scale: float, seed: int
) -> Path:
    """The bed of ``scenario`` built from ``cfg`` with ``bed.radius`` times ``scale`` and
    ``seed``, at ``workdir``/``name``/{scenario}.npz (built once, reused after)."""
    from dozerlab.scenarios.build import build_bed

    path = workdir / name / f"{scenario}.npz"
    if path.exists():
        print(f"  {name}: {scenario} bed reused from {path}")
        return path
    c = copy.deepcopy(cfg)
    c["bed"]["radius"] = float(cfg["bed"]["radius"]) * scale
    c["seed"] = seed
    bed = build_bed(scenario, c, progress=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    bed.save(path)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--radius-scales", type=float, nargs="+", default=[1.26, 1.5])
    ap.add_argument("--repour", action="store_true", help="also the fine bed poured again")
    ap.add_argument("--dynamics", nargs="+", default=["replay", "ridge"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args()
    if any(s <= 0 for s in args.radius_scales):
        ap.error(f"--radius-scales must be > 0, got {args.radius_scales}")
    os.environ["DOZERLAB_MLFLOW"] = "0"
    set_threads(args.threads)
    cfg = load_config(args.config)
    res = args.results
    seed = int(cfg["seed"])
    variants = [(f"radius x{s:g}", s, seed) for s in args.radius_scales]
    if args.repour:
        variants.insert(0, ("repoured", 1.0, seed + 1))
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        for pt in (p for p in P.sweep_points(cfg) if p.role != "train"):
            fine_path = P.bed_path(res, pt.scenario)
            fine = Bed.load(fine_path)
            sigma = surface_sigma(fine.radii)

            def surface(b: Bed, fine: Bed = fine, sigma: float = sigma) -> np.ndarray:
                return smoothed_surface(b.positions, b.radii, fine.length, fine.width, sigma)

            h_bed = surface(fine)
            h_ndem = surface(Bed.load(P.state_path(res, pt)))
            twin = height_accuracy(surface(Bed.load(P.twin_path(res, pt, "npz"))), h_ndem, h_bed)
            print(f"{pt.scenario} {pt.name} ({pt.role}): {fine.radii.size} grains, twin {twin:.3f}")
            beds = [("fine", fine_path)] + [
                (name, variant_bed(pt.scenario, cfg, work, name, scale=s, seed=sd))
                for name, s, sd in variants
            ]
            for name, path in beds:
                b = Bed.load(path)
                h_b = surface(b)
                off = np.abs(h_b - h_bed).sum() / np.abs(h_ndem - h_bed).sum()
                print(
                    f"  {name}: {b.radii.size} grains, its surface off the fine bed's by {off:.3f}"
                )
                for model in args.dynamics:
                    out = work / "runs" / f"{pt.scenario}_{pt.name}_{name}_{model}".replace(" ", "")
                    r = run_loop(
                        model,
                        res,
                        cfg,
                        pt,
                        path,
                        P.trajectory_path(res, pt),
                        P.field_path(res, pt),
                        out,
                    )
                    h = surface(Bed.load(out.with_suffix(".npz")))
                    acc = height_accuracy(h, h_ndem, h_bed)
                    # the fine bed moved as this bed's loop moved its own: what a loop that
                    # kept the fine grains at rest and moved coarse ones would reach at best
                    kept = height_accuracy(h_bed + (h - h_b), h_ndem, h_bed)
                    phases = ", ".join(
                        f"{k[3:]} {v:.2f}" for k, v in r.items() if k.startswith("ms_")
                    )
                    print(
                        f"    {model}: loop {r['wall_time_s']:.2f} s, smoothed surface {acc:.3f} "
                        f"(skill {acc / twin:.3f}; the fine bed moved by its change "
                        f"{kept / twin:.3f}), largest overlap {r['max_overlap']:.3f} r; "
                        f"ms a row: {phases}"
                    )


if __name__ == "__main__":
    main()
