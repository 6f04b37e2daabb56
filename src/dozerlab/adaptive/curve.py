"""The learning curve: held-out force error against the number of NDEM training runs.

Each *design* is a sequence of nested training sets: the adaptive design's rounds (round 0,
then rounds 0-1, …), the grid (all its runs), and random designs of the adaptive design's sizes
drawn from its candidates (one permutation per seed, its first n runs: a random design grows as
the adaptive one does). For each training set the curve's force model is trained and measured
on the same held-out points; a row per (design, seed, runs).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.learn.data import StoreData
from dozerlab.sweep import SweepPoint

#: The columns of ``learning_curve.csv``; errors are relative RMSEs of the pushing force
#: (force_x) on the held-out points, all together and per group, as fractions.
COLUMNS = (
    "design",
    "seed",
    "runs",
    "model",
    "heldout_force_rel_rmse",
    "interpolation_force_rel_rmse",
    "extrapolation_force_rel_rmse",
)


@dataclass(frozen=True)
class Design:
    """A design's name, its seed (-1 when not random) and its nested training sets."""

    name: str
    seed: int
    sets: tuple[tuple[SweepPoint, ...], ...]


def cumulative(rounds: Sequence[Sequence[SweepPoint]]) -> tuple[tuple[SweepPoint, ...], ...]:
    """The adaptive design's training sets: rounds 0..r for each r."""
    out: list[tuple[SweepPoint, ...]] = []
    acc: list[SweepPoint] = []
    for r in rounds:
        acc += list(r)
        out.append(tuple(acc))
    return tuple(out)


def random_designs(
    pool: Sequence[SweepPoint], sizes: Sequence[int], seeds: Sequence[int]
) -> list[Design]:
    """Random designs of ``sizes`` drawn from ``pool``: per seed one permutation of the pool,
    whose first n points are the design of size n (sizes above the pool's are left out)."""
    designs = []
    for seed in seeds:
        order = np.random.default_rng(seed).permutation(len(pool))
        sets = tuple(tuple(pool[i] for i in order[:n]) for n in sizes if n <= len(pool))
        designs.append(Design("random", int(seed), sets))
    return designs


def rel_rmse(result: Mapping[str, Any]) -> float:
    """The pushing force's relative RMSE of an :func:`~dozerlab.learn.validate.evaluate` result."""
    return float(result["overall"]["force_x"]["rel_rmse"])


def curve_rows(
    designs: Sequence[Design],
    stores: Mapping[SweepPoint, StoreData],
    held_out: Mapping[str, Sequence[StoreData]],
    config: Mapping[str, Any],
    model: str,
) -> list[dict[str, Any]]:
    """Train ``model`` on each design's training sets (stores by point, roles ignored) and measure
    it on the held-out stores of each group; one row of :data:`COLUMNS` per set. A training set
    met twice (the grid's and a random design's full pool, say) is trained once."""
    from dozerlab.learn.train import train_model
    from dozerlab.learn.validate import evaluate

    done: dict[frozenset[tuple[str, str]], dict[str, float]] = {}
    every = [s for group in held_out.values() for s in group]
    rows = []
    for d in designs:
        for pts in d.sets:
            key = frozenset(p.key for p in pts)
            if key not in done:
                trained = train_model(model, [stores[_plain(p)] for p in pts], dict(config))
                errors = {"heldout": rel_rmse(evaluate(trained.model, every))}
                for g, group in held_out.items():
                    errors[g] = (
                        rel_rmse(evaluate(trained.model, list(group))) if group else float("nan")
                    )
                done[key] = errors
            e = done[key]
            rows.append(
                {
                    "design": d.name,
                    "seed": d.seed,
                    "runs": len(pts),
                    "model": model,
                    "heldout_force_rel_rmse": e["heldout"],
                    "interpolation_force_rel_rmse": e.get("interpolation", float("nan")),
                    "extrapolation_force_rel_rmse": e.get("extrapolation", float("nan")),
                }
            )
    return rows


def _plain(p: SweepPoint) -> SweepPoint:
    return SweepPoint(p.scenario, p.speed, p.depth)


def write_curve(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """``learning_curve.csv``: :data:`COLUMNS`, errors with 6 significant digits."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: f"{v:.6g}" if isinstance(v, float) else v for k, v in r.items()})


def read_curve(path: str | Path) -> list[dict[str, Any]]:
    """The rows of ``learning_curve.csv``, numbers parsed."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return [
        {
            k: (v if k in ("design", "model") else int(v) if k in ("seed", "runs") else float(v))
            for k, v in r.items()
        }
        for r in rows
    ]


def mean_by_size(rows: Sequence[Mapping[str, Any]], design: str) -> dict[int, float]:
    """A design's mean held-out error per number of runs (over its seeds)."""
    out: dict[int, list[float]] = {}
    for r in rows:
        if r["design"] == design:
            out.setdefault(int(r["runs"]), []).append(float(r["heldout_force_rel_rmse"]))
    return {n: float(np.mean(v)) for n, v in sorted(out.items())}
