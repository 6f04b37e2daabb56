"""The acquisition on hand-made cases, the designs and the points files."""

import math

import numpy as np
import pytest

from dozerlab.adaptive import design
from dozerlab.adaptive.design import Box, Scored
from dozerlab.config import load_config
from dozerlab.runtime import DozerlabError
from dozerlab.sweep import SweepPoint

BOX = Box((1.0, 2.0), (0.1, 0.2))


def lattice(n: int, scenario: str = "hill") -> list[SweepPoint]:
    return design.candidates([scenario], BOX, {"kind": "lattice", "count": n, "seed": 0})


def test_a_known_bump_of_disagreement_is_picked():
    # A 5 × 5 lattice of runs whose pushing force is a plane but for one bump at (1.5 m/s,
    # 0.15 m): the members that leave the bump's run out disagree with those that keep it, most
    # near the bump, so the candidates next to it score highest.
    runs = {}
    for p in lattice(5):
        bump = 5000.0 if (p.speed, p.depth) == (1.5, 0.15) else 0.0
        y = np.array([-2000.0 * p.speed - 10000.0 * p.depth - bump, 1000.0])
        runs[p] = (y, np.array([50.0, 50.0]))
    pool = [p for p in lattice(9) if p not in runs]
    scored = design.score_candidates(runs, pool, BOX, members=32, seed=0)
    best = max(scored, key=lambda s: s.score)
    assert design.distance(BOX, best.point, SweepPoint("hill", 1.5, 0.15)) <= 0.2
    assert "mean force_x" in best.why and "run-to-run" in best.why
    far = [s for s in scored if design.distance(BOX, s.point, SweepPoint("hill", 1.5, 0.15)) > 0.6]
    assert best.score > 1.5 * max(s.score for s in far)


def test_the_score_is_relative_to_ndem_noise():
    runs = {
        p: (np.array([p.speed * 1000.0 * (1 + (p.depth > 0.15)), 0.0]), np.array([10.0, 10.0]))
        for p in lattice(3)
    }
    pool = [p for p in lattice(5) if p not in runs]
    quiet = design.score_candidates(runs, pool, BOX, members=16, seed=1)
    noisy = {p: (y, 10 * n) for p, (y, n) in runs.items()}
    loud = design.score_candidates(noisy, pool, BOX, members=16, seed=1)
    assert [round(a.score / b.score, 6) for a, b in zip(quiet, loud, strict=True)] == [10.0] * len(
        pool
    )


def test_a_round_keeps_its_spacing_and_avoids_earlier_runs():
    # every candidate scores by closeness to one spot: without spacing all picks would pile there
    spot = SweepPoint("hill", 1.5, 0.15)
    scored = [
        Scored(p, 1.0 / (0.01 + design.distance(BOX, p, spot)), "near the spot")
        for p in lattice(11)
    ]
    taken = [SweepPoint("hill", 1.0, 0.1)]
    picks = design.select(scored, taken, BOX, count=4, min_spacing=0.3)
    assert len(picks) == 4
    assert picks[0].point == spot
    for i, a in enumerate(picks):
        assert design.distance(BOX, a.point, taken[0]) >= 0.3
        for b in picks[i + 1 :]:
            assert design.distance(BOX, a.point, b.point) >= 0.3 - 1e-9
    assert picks[0].why.endswith("rank 1 of 121 candidates")


def test_a_round_takes_fewer_points_when_none_is_far_enough():
    scored = [Scored(p, 1.0, "x") for p in lattice(3)]
    assert len(design.select(scored, [], BOX, count=9, min_spacing=1.5)) == 1


def test_spacing_never_crosses_scenarios():
    a, b = SweepPoint("hill", 1.0, 0.1), SweepPoint("step", 1.0, 0.1)
    assert math.isinf(design.distance(BOX, a, b))
    picks = design.select([Scored(a, 2.0, ""), Scored(b, 1.0, "")], [], BOX, 2, 0.5)
    assert [p.point for p in picks] == [a, b]


def test_corners_and_lhs_designs_lie_in_the_box():
    corners = design.initial_design(
        ["hill", "step"], BOX, {"kind": "corners", "size": 4, "seed": 0}
    )
    assert {(p.speed, p.depth) for p in corners} == {(1.0, 0.1), (2.0, 0.1), (1.0, 0.2), (2.0, 0.2)}
    assert len(corners) == 8
    lhs = design.initial_design(["hill"], BOX, {"kind": "lhs", "size": 6, "seed": 3})
    assert len(lhs) == 6
    u = BOX.to_unit(np.array([p.speed for p in lhs]), np.array([p.depth for p in lhs]))
    # one point per stratum along each axis
    for axis in (0, 1):
        assert sorted(np.floor(u[:, axis] * 6).astype(int)) == list(range(6))
    again = design.initial_design(["hill"], BOX, {"kind": "lhs", "size": 6, "seed": 3})
    assert again == lhs


def test_a_lattice_of_the_grids_count_is_the_grid():
    cfg = load_config({"sweep": {"speeds": [0.75, 1.0, 1.25], "depths": [0.03, 0.06, 0.09]}})
    box = Box.of(cfg["sweep"])
    pts = design.candidates(["hill"], box, {"kind": "lattice", "count": 3, "seed": 0})
    assert {(p.speed, p.depth) for p in pts} == {
        (v, d) for v in (0.75, 1.0, 1.25) for d in (0.03, 0.06, 0.09)
    }
    rnd = design.candidates(["hill"], box, {"kind": "random", "count": 7, "seed": 2})
    assert len(rnd) == 7 and all(0.75 <= p.speed <= 1.25 and 0.03 <= p.depth <= 0.09 for p in rnd)


def test_noise_is_the_standard_error_of_a_runs_mean():
    rng = np.random.default_rng(0)
    force = rng.normal(0.0, 100.0, (800, 3))
    noise = design.run_noise(force)
    assert noise.shape == (2,)
    assert 100 / np.sqrt(800) / 2 < noise[0] < 100 / np.sqrt(800) * 2
    assert design.run_summaries(np.ones((5, 3)) * [1.0, 2.0, 3.0]).tolist() == [1.0, 3.0]


def test_the_ensemble_needs_two_runs():
    with pytest.raises(DozerlabError, match="at least 2 runs"):
        design.ensemble_predictions(np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((3, 2)), 4, 0)


def test_points_files_read_back(tmp_path):
    rows = [
        Scored(SweepPoint("hill", 1.25, 0.06), 2.5, "spread, rank 1"),
        Scored(SweepPoint("step", 1.0, 0.03), float("nan"), "initial"),
    ]
    design.write_points(tmp_path / "points.csv", rows)
    assert (tmp_path / "points.csv").read_text().splitlines()[0] == "scenario,speed,depth,score,why"
    back = design.read_points(tmp_path / "points.csv")
    assert [r.point for r in back] == [r.point for r in rows]
    assert back[0].score == 2.5 and math.isnan(back[1].score) and back[0].why == rows[0].why
    (tmp_path / "other.csv").write_text("a,b\n")
    with pytest.raises(DozerlabError, match="not a round's points"):
        design.read_points(tmp_path / "other.csv")


def test_held_out_points_are_never_candidates():
    held = {"scenario": "hill", "speed": 0.875, "depth": 0.045}
    sweep = {
        "speeds": [0.75, 1.25],
        "depths": [0.03, 0.09],
        "scenarios": ["hill"],
        "interpolation": [held],
    }
    cfg = load_config(
        {"sweep": {**sweep, "adaptive": {"candidates": {"kind": "lattice", "count": 5}}}}
    )
    pool = design.candidate_pool(cfg)
    assert len(pool) == 24 and SweepPoint("hill", 0.875, 0.045) not in pool
