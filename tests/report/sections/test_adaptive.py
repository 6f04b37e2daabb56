"""The adaptive-sweep section: the rounds on the sweep map, why each point was picked, the
learning curve and its verdict against the grid and random designs."""

import math

from dozerlab import sweep as P
from dozerlab.adaptive.curve import write_curve
from dozerlab.adaptive.design import Scored, write_points
from dozerlab.config import load_config
from dozerlab.report.sections import adaptive
from dozerlab.sweep import SweepPoint
from tests.helpers import SMALL_SWEEP, report_context

CFG = load_config(SMALL_SWEEP)


def rows(design, seed, runs, err, loop=float("nan")):
    return {
        "design": design,
        "seed": seed,
        "runs": runs,
        "model": "linear",
        "heldout_force_rel_rmse": err,
        "interpolation_force_rel_rmse": err,
        "extrapolation_force_rel_rmse": err,
        "reduced_force_model": "" if math.isnan(loop) else "linear",
        "reduced_force_lp_rel_rmse": loop,
        "twin_force_lp_rel_rmse": loop if math.isnan(loop) else 0.2,
        "reduced_force_lp_rel_rmse_skill": loop / 0.2,
    }


def test_no_rounds_no_section(tmp_path):
    ctx = report_context(CFG, tmp_path)
    assert adaptive.render(ctx) is None and adaptive.verdict(ctx) is None


def test_rounds_why_and_the_curve_with_its_verdict(tmp_path):
    for r, point in enumerate([SweepPoint("hill", 0.5, 0.1), SweepPoint("hill", 0.75, 0.1)]):
        path = P.adaptive_path("adaptive_points", tmp_path, r)
        path.parent.mkdir(parents=True)
        write_points(path, [Scored(point, 1.5 if r else float("nan"), f"picked in round {r}")])
    ctx = report_context(CFG, tmp_path)
    body = adaptive.render(ctx)
    assert "picked in round 1" in body and "<img" in body
    assert "learning curve is not built yet" in body
    curve = [rows("adaptive", -1, 1, 0.12), rows("adaptive", -1, 2, 0.10), rows("grid", -1, 2, 0.1)]
    curve += [rows("random", 1, 2, 0.14), rows("random", 2, 2, 0.12)]
    write_curve(tmp_path / P.PATHS["learning_curve"], curve)
    assert adaptive.render(ctx).count("<img") == 2
    assert adaptive.verdict(ctx) == (
        "With 2 NDEM training runs the adaptive design's held-out force_x error is 10.0 %; the grid's 2 "
        "runs reach 10.0 % (reached within 5 %); random designs of 2 runs 13.0 % on average."
    )


def test_the_reduced_simulations_figures_join_the_verdict_and_the_table(tmp_path):
    path = P.adaptive_path("adaptive_points", tmp_path, 0)
    path.parent.mkdir(parents=True)
    write_points(path, [Scored(SweepPoint("hill", 0.5, 0.1), float("nan"), "initial design")])
    curve = [rows("adaptive", -1, 1, 0.12, 0.09), rows("grid", -1, 1, 0.12, 0.09)]
    write_curve(tmp_path / P.PATHS["learning_curve"], curve)
    ctx = report_context(CFG, tmp_path)
    assert adaptive.verdict(ctx).endswith(
        "In the replay loop the reduced simulation's low-passed force_x error is 9.0 % "
        "(the grid's 9.0 %, the twins' 20.0 %)."
    )
    body = adaptive.render(ctx)
    assert "reduced: low-passed force_x rel. RMSE (%)" in body and "0.45" in body
