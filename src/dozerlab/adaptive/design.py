"""Adaptive designs: the initial points, the candidates, and the acquisition that picks the next.

Points live in a box per scenario, the ranges of ``sweep.speeds`` (m/s) and ``sweep.depths``
(m); distances and spacings are measured in *normalised units*, each axis mapped onto [0, 1]
(:class:`Box`), so a spacing of 0.5 is half a range whatever the units.

The acquisition asks an ensemble where it disagrees most. Each member is a smooth surrogate of
a run's *summaries* (its mean pushing force and mean vertical force, N) over (speed, depth),
fitted to a bootstrap resample of the scenario's NDEM runs: a linear trend plus a Gaussian-kernel
interpolant of the residuals. Where the members' predictions spread most, relative to NDEM's
own run-to-run spread of that summary (:func:`run_noise`), one more NDEM run teaches the most.
A greedy pass then takes the best candidates a minimum spacing apart (:func:`select`).
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.runtime import DozerlabError
from dozerlab.sweep import SweepPoint, fmt_number

#: The columns of a round's ``points.csv``.
COLUMNS = ("scenario", "speed", "depth", "score", "why")
#: The run summaries the ensemble predicts: (name, force component index), force in N.
SUMMARIES = (("mean force_x", 0), ("mean force_z", 2))
#: Decimals kept of a design's speeds (m/s) and depths (m): a lattice's 0.06 is not 0.060000000000000005.
DECIMALS = 6
#: Length scale of the members' Gaussian kernel, in normalised units.
LENGTH_SCALE = 0.35
#: The kernel fit's nugget, relative to the kernel's unit diagonal: with 1e-3 the fit to a
#: 5 × 5 lattice of runs swung between them, and the spread peaked at the box's edge, not at a bump.
NUGGET = 1e-2
#: Blocks a run is split into for the standard error of its mean (:func:`run_noise`).
NOISE_BLOCKS = 8


@dataclass(frozen=True)
class Box:
    """The ranges of a sweep: speeds ``(lo, hi)`` in m/s and depths ``(lo, hi)`` in m."""

    speed: tuple[float, float]
    depth: tuple[float, float]

    @classmethod
    def of(cls, sweep: Mapping[str, Any]) -> Box:
        """The box of a validated config's ``sweep`` section (its speeds' and depths' ranges)."""
        v, d = sweep["speeds"], sweep["depths"]
        return cls((float(min(v)), float(max(v))), (float(min(d)), float(max(d))))

    def to_unit(self, speed: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(N, 2) normalised coordinates of speeds (m/s) and depths (m); a range of one value maps to 0."""
        return np.stack(
            [
                _unit(np.asarray(speed, float), *self.speed),
                _unit(np.asarray(depth, float), *self.depth),
            ],
            axis=-1,
        )

    def from_unit(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Speeds (m/s) and depths (m) of (N, 2) normalised coordinates, rounded to :data:`DECIMALS`."""
        u = np.asarray(u, float).reshape(-1, 2)
        speed = self.speed[0] + u[:, 0] * (self.speed[1] - self.speed[0])
        depth = self.depth[0] + u[:, 1] * (self.depth[1] - self.depth[0])
        return np.round(speed, DECIMALS), np.round(depth, DECIMALS)


def _unit(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return (x - lo) / (hi - lo) if hi > lo else np.zeros_like(x)


def _points(scenario: str, box: Box, u: np.ndarray) -> list[SweepPoint]:
    """Distinct sweep points of normalised coordinates ``u``, in order."""
    speed, depth = box.from_unit(u)
    points = [SweepPoint(scenario, float(v), float(d)) for v, d in zip(speed, depth, strict=True)]
    return list(dict.fromkeys(points))


def initial_design(
    scenarios: Sequence[str], box: Box, initial: Mapping[str, Any]
) -> list[SweepPoint]:
    """Round 0: per scenario, the box's corners (``kind: corners``, 4 points, fewer when a range
    is one value) or ``size`` points of a Latin hypercube (``kind: lhs``, seeded by ``seed``)."""
    if initial["kind"] == "corners":
        u = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
        return [p for s in scenarios for p in _points(s, box, u)]
    rng = np.random.default_rng(initial["seed"])
    points: list[SweepPoint] = []
    for s in scenarios:
        n = initial["size"]
        # one point in each of n strata per axis, the strata paired at random
        u = np.stack([(rng.permutation(n) + rng.random(n)) / n for _ in range(2)], axis=-1)
        points += _points(s, box, u)
    return points


def candidates(scenarios: Sequence[str], box: Box, spec: Mapping[str, Any]) -> list[SweepPoint]:
    """The points a round may pick, per scenario: a ``count`` × ``count`` lattice spanning the box
    (``kind: lattice``; with ``count`` equal to the grid's points per axis, the grid's own
    points) or ``count`` uniform random points (``kind: random``, seeded by ``seed``)."""
    n = spec["count"]
    if spec["kind"] == "lattice":
        axis = np.linspace(0.0, 1.0, n)
        u = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2)
        return [p for s in scenarios for p in _points(s, box, u)]
    rng = np.random.default_rng(spec["seed"])
    return [p for s in scenarios for p in _points(s, box, rng.random((n, 2)))]


def run_summaries(force: np.ndarray) -> np.ndarray:
    """A run's summaries (:data:`SUMMARIES`, N) from its (T, 3) blade force in N."""
    return np.array([float(np.mean(force[:, i])) for _, i in SUMMARIES])


def run_noise(force: np.ndarray, blocks: int = NOISE_BLOCKS) -> np.ndarray:
    """NDEM's run-to-run spread of each summary (N), estimated from one run: the standard error
    of its mean from ``blocks`` consecutive blocks of rows. The spread of the block means is
    taken from their successive differences (over sqrt 2), so the force's slow rise along the
    path is not counted as noise. Two runs of one point differing only in their grains' chance
    arrangement differ in their means by about this much."""
    means = np.array(
        [[np.mean(b[:, i]) for _, i in SUMMARIES] for b in np.array_split(force, blocks)]
    )
    return np.std(np.diff(means, axis=0), axis=0, ddof=1) / np.sqrt(2 * blocks)


def _member_fit(u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A member's surrogate fitted to runs at ``u`` (N, 2) with summaries ``y`` (N, S): the
    linear trend's coefficients (3, S) and the kernel interpolant's weights (N, S) at ``u``."""
    a = np.column_stack([np.ones(len(u)), u])
    trend = np.linalg.lstsq(a, y, rcond=None)[0]
    k = _kernel(u, u) + NUGGET * np.eye(len(u))
    weights = np.linalg.solve(k, y - a @ trend)
    return trend, weights, u


def _member_predict(fit: tuple[np.ndarray, np.ndarray, np.ndarray], x: np.ndarray) -> np.ndarray:
    trend, weights, u = fit
    return np.column_stack([np.ones(len(x)), x]) @ trend + _kernel(x, u) @ weights


def _kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)
    return np.exp(-0.5 * d2 / LENGTH_SCALE**2)


def ensemble_predictions(
    u: np.ndarray, y: np.ndarray, x: np.ndarray, members: int, seed: int
) -> np.ndarray:
    """(members, M, S) predictions at ``x`` (M, 2) of the ensemble fitted to runs at ``u`` (N, 2)
    with summaries ``y`` (N, S): each member on a bootstrap resample of the runs (drawn again
    until it holds two distinct runs; duplicates merged)."""
    if len(u) < 2:
        raise DozerlabError(f"the ensemble needs at least 2 runs of a scenario, got {len(u)}")
    rng = np.random.default_rng(seed)
    out = np.empty((members, len(x), y.shape[1]))
    for m in range(members):
        while len(idx := np.unique(rng.integers(0, len(u), len(u)))) < 2:
            pass
        out[m] = _member_predict(_member_fit(u[idx], y[idx]), x)
    return out


@dataclass(frozen=True)
class Scored:
    """A candidate and its acquisition score: the largest over the summaries of the members'
    spread (standard deviation, N) over NDEM's run-to-run spread (N), and what set it."""

    point: SweepPoint
    score: float
    why: str


def score_candidates(
    runs: Mapping[SweepPoint, tuple[np.ndarray, np.ndarray]],
    pool: Sequence[SweepPoint],
    box: Box,
    members: int,
    seed: int,
) -> list[Scored]:
    """Score each candidate of ``pool`` with the ensemble of its scenario's runs.

    ``runs`` maps each NDEM run's point to its summaries (S,) and their noise (S,) in N
    (:func:`run_summaries`, :func:`run_noise`). The noise of a scenario is the median over its
    runs (one run's estimate is itself noisy), floored at 1 mN.
    """
    scored: list[Scored] = []
    for s in dict.fromkeys(p.scenario for p in pool):
        mine = [p for p in runs if p.scenario == s]
        cands = [p for p in pool if p.scenario == s]
        u = box.to_unit(np.array([p.speed for p in mine]), np.array([p.depth for p in mine]))
        y = np.array([runs[p][0] for p in mine])
        noise = np.maximum(np.median(np.array([runs[p][1] for p in mine]), axis=0), 1e-3)
        x = box.to_unit(np.array([p.speed for p in cands]), np.array([p.depth for p in cands]))
        spread = ensemble_predictions(u, y, x, members, seed).std(axis=0, ddof=1)
        ratio = spread / noise
        for j, p in enumerate(cands):
            k = int(np.argmax(ratio[j]))
            name = SUMMARIES[k][0]
            scored.append(
                Scored(
                    p,
                    float(ratio[j, k]),
                    f"{members} members' {name} spread {spread[j, k]:.0f} N = "
                    f"{ratio[j, k]:.2f} x NDEM's run-to-run spread ({noise[k]:.0f} N)",
                )
            )
    return scored


def distance(box: Box, a: SweepPoint, b: SweepPoint) -> float:
    """Normalised distance of two points (infinite across scenarios)."""
    if a.scenario != b.scenario:
        return float("inf")
    ua, ub = box.to_unit(np.array([a.speed, b.speed]), np.array([a.depth, b.depth]))
    return float(np.hypot(*(ua - ub)))


def select(
    scored: Iterable[Scored],
    taken: Iterable[SweepPoint],
    box: Box,
    count: int,
    min_spacing: float,
) -> list[Scored]:
    """Up to ``count`` candidates, highest score first, each at least ``min_spacing`` (normalised)
    from every point of ``taken`` (the runs so far) and from the round's earlier picks; ties in
    score go to the earlier candidate. The ``why`` of each pick adds its rank."""
    ranked = sorted(enumerate(scored), key=lambda t: (-t[1].score, t[0]))
    pool = len(ranked)
    chosen: list[Scored] = []
    near = list(taken)
    for rank, (_, c) in enumerate(ranked, start=1):
        if len(chosen) == count:
            break
        # a lattice's neighbours at exactly min_spacing count as far enough despite rounding
        if any(distance(box, c.point, q) < min_spacing - 1e-9 for q in near):
            continue
        chosen.append(Scored(c.point, c.score, f"{c.why}; rank {rank} of {pool} candidates"))
        near.append(c.point)
    return chosen


def write_points(path: Path, rows: Sequence[Scored]) -> None:
    """A round's ``points.csv`` (:data:`COLUMNS`; speed m/s, depth m in canonical spelling)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in rows:
            p = r.point
            w.writerow(
                [p.scenario, fmt_number(p.speed), fmt_number(p.depth), f"{r.score:.6g}", r.why]
            )


def read_points(path: str | Path) -> list[Scored]:
    """The rows of a round's ``points.csv``; an error naming the file if its header is not :data:`COLUMNS`."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(rows[0]) != COLUMNS:
        raise DozerlabError(f"{path}: not a round's points (header {','.join(COLUMNS)})")
    return [Scored(SweepPoint(r[0], float(r[1]), float(r[2])), float(r[3]), r[4]) for r in rows[1:]]


def round_zero(cfg: Mapping[str, Any]) -> list[Scored]:
    """Round 0 of a validated config's ``sweep.adaptive``: the initial design, unscored."""
    sweep, ad = cfg["sweep"], cfg["sweep"]["adaptive"]
    why = {
        "corners": "initial design: a corner of the box",
        "lhs": "initial design: Latin hypercube",
    }
    box = Box.of(sweep)
    points = initial_design(sweep["scenarios"], box, ad["initial"])
    return [Scored(p, float("nan"), why[ad["initial"]["kind"]]) for p in points]


def next_round(
    cfg: Mapping[str, Any],
    round_index: int,
    taken: Sequence[SweepPoint],
    runs: Mapping[SweepPoint, tuple[np.ndarray, np.ndarray]],
) -> list[Scored]:
    """Round ``round_index`` (>= 1): ``sweep.adaptive.per_round`` candidates picked by the
    ensemble fitted to ``runs`` (summaries and noise of each NDEM run, :func:`score_candidates`),
    away from ``taken`` (every point of the earlier rounds). The bootstrap is seeded by the
    config's ``seed`` and the round."""
    sweep, ad = cfg["sweep"], cfg["sweep"]["adaptive"]
    box = Box.of(sweep)
    done = set(taken)
    pool = [p for p in candidate_pool(cfg) if p not in done]
    scored = score_candidates(runs, pool, box, ad["members"], int(cfg["seed"]) + round_index)
    return select(scored, taken, box, ad["per_round"], ad["min_spacing"])


def candidate_pool(cfg: Mapping[str, Any]) -> list[SweepPoint]:
    """A validated config's candidates (``sweep.adaptive.candidates``) but its held-out points,
    which no design may train on (a lattice of 5 per axis holds the default sweep's
    interpolation points)."""
    sweep = cfg["sweep"]
    held = {
        SweepPoint(h["scenario"], float(h["speed"]), float(h["depth"]))
        for g in ("interpolation", "extrapolation")
        for h in sweep[g]
    }
    pool = candidates(sweep["scenarios"], Box.of(sweep), sweep["adaptive"]["candidates"])
    return [p for p in pool if p not in held]
