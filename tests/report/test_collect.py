"""Each sweep point's numbers and figures, read from its store and trajectory plot."""

import pytest

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.collect import PointSummary, point_figures, summarize
from tests.helpers import SMALL_SWEEP, png_file, report_store

POINT = P.sweep_points(load_config(SMALL_SWEEP))[0]


def test_a_store_gives_its_counts_times_and_forces(tmp_path):
    report_store(P.field_path(tmp_path, POINT), POINT, steps=4, wall_time=3.0)
    s = summarize(tmp_path, POINT)
    assert s.built and s.particles == 321
    assert s.steps == 4 * 2  # rows × sample_every
    assert s.simulated == pytest.approx(0.04) and s.wall_time == 3.0
    assert s.slowdown == pytest.approx(3.0 / 0.04)
    # |F| of (1000, 0, 300) N on three rows and of (2000, 0, 300) N on the last
    small, big = (1000**2 + 300**2) ** 0.5, (2000**2 + 300**2) ** 0.5
    assert s.mean_force == pytest.approx((3 * small + big) / 4)
    assert s.peak_force == pytest.approx(big)


def test_a_missing_store_is_a_row_of_unknowns(tmp_path):
    s = summarize(tmp_path, POINT)
    assert s == PointSummary(POINT)
    assert not s.built and s.slowdown is None
    assert PointSummary(POINT, wall_time=2.0, simulated=0.0).slowdown is None


def test_figures_are_the_trajectory_slice_and_force_of_what_exists(tmp_path):
    assert point_figures(tmp_path, POINT) == []
    png_file(P.trajectory_path(tmp_path, POINT, "png"), "path")
    only = point_figures(tmp_path, POINT)
    assert len(only) == 1 and "blade trajectory" in only[0]
    report_store(P.field_path(tmp_path, POINT), POINT)
    figures = point_figures(tmp_path, POINT)
    assert len(figures) == 3
    assert "t = 0.04 s" in figures[1]  # the middle row of six, 0.01 s apart from 0.01 s
    assert "blade force (kN) and torque about the tip (kN·m)" in figures[2]
    assert all('src="data:image/png;base64,' in f for f in figures)
