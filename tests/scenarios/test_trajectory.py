import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.scenarios.blade import start_tip
from dozerlab.scenarios.trajectory import Trajectory, plan_trajectory, walk_path


def surface_at(traj, x):
    return np.interp(x, traj.height_x, traj.height_filtered)


def cutting_region(traj, config, margin=0.02):
    """Steps past the approach whose surface is clearly above or below the goal height."""
    x = traj.position[:, 0]
    # The ease is applied at the path's vertices, so it is complete one height cell later.
    cell = traj.height_x[1] - traj.height_x[0]
    approach_end = (
        traj.position[0, 0] + config["trajectory"]["approach_steps"] * traj.speed * traj.dt + cell
    )
    h = surface_at(traj, x)
    past = x > approach_end
    return past & (h >= traj.goal_height + margin), past & (h < traj.goal_height - margin), h


@pytest.mark.parametrize(("speed", "depth"), [(1.0, 0.1), (0.5, 0.05), (1.5, 0.15)])
def test_hill_path_follows_the_rule_at_constant_speed(hill_bed, config, speed, depth):
    traj = plan_trajectory(hill_bed, speed, depth, config)
    above, below, h = cutting_region(traj, config)
    z = traj.position[:, 2]
    assert above.sum() > 20 and below.sum() > 20
    np.testing.assert_allclose(h[above] - z[above], depth, atol=1e-6)
    np.testing.assert_allclose(z[below] - h[below], depth, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(traj.velocity, axis=1), speed, rtol=1e-9)
    np.testing.assert_allclose(traj.velocity[:, 1], 0.0)


def test_step_path_cuts_the_shelf_and_rides_over_the_low_side(step_bed, config):
    traj = plan_trajectory(step_bed, 1.0, 0.12, config)
    above, below, h = cutting_region(traj, config)
    x, z = traj.position[:, 0], traj.position[:, 2]
    assert x[above].max() < 2.05 and x[below].min() > 1.95 and x[below].max() > 3.0
    np.testing.assert_allclose(h[above] - z[above], 0.12, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(traj.velocity, axis=1), 1.0, rtol=1e-9)


@pytest.mark.parametrize("bed_name", ["hill_bed", "step_bed"])
def test_path_ends_on_flat_bed_before_the_end_wall(request, config, bed_name):
    bed = request.getfixturevalue(bed_name)
    traj = plan_trajectory(bed, 1.0, 0.1, config)
    end = bed.length - config["trajectory"]["end_margin"]
    assert end - traj.speed * traj.dt <= traj.position[-1, 0] <= end
    near = np.abs(traj.height_x - end) < 0.2
    assert np.ptp(traj.height_filtered[near]) < 0.02


def test_starts_behind_the_bed_and_eases_onto_the_path(hill_bed, config):
    traj = plan_trajectory(hill_bed, 1.0, 0.1, config)
    np.testing.assert_array_equal(traj.position[0], start_tip(hill_bed, config))
    back = min(0.0, (hill_bed.positions[:, 0] - hill_bed.radii).min())
    assert traj.position[0, 0] == pytest.approx(back - config["blade"]["start_gap"])
    n = config["trajectory"]["approach_steps"]
    # Smooth: the velocity turns by a small amount each step during the approach.
    assert np.abs(np.diff(traj.velocity[: n + 2], axis=0)).max() < 0.25 * traj.speed


def test_integrating_velocities_reproduces_positions_exactly(hill_bed, config, tmp_path):
    traj = plan_trajectory(hill_bed, 0.7, 0.08, config)
    traj.save_csv(tmp_path / "t.csv")
    back = Trajectory.load_csv(tmp_path / "t.csv")
    np.testing.assert_array_equal(back.position, traj.position)
    np.testing.assert_array_equal(back.velocity, traj.velocity)
    assert back.dt == pytest.approx(config["solver"]["dt"])
    assert back.speed == pytest.approx(0.7)
    p = back.position[0].copy()
    for i, v in enumerate(back.velocity):
        p = p + back.dt * v
        assert np.array_equal(p, back.position[i + 1])
    np.testing.assert_array_equal(back.time, np.arange(len(back.time)) * back.dt)
    header = (tmp_path / "t.csv").read_text().splitlines()
    assert header[0] == "step,time,x,y,z,vx,vy,vz"
    assert header[-2].endswith(",0,0,0")
    assert header[-1].startswith("# sha256 ")  # np.loadtxt skips it as a comment


def test_walk_path_keeps_chord_length_around_corners():
    path = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.5], [2.0, 0.5]])
    pts = walk_path(path, 0.03)
    np.testing.assert_allclose(np.linalg.norm(np.diff(pts, axis=0), axis=1), 0.03, rtol=1e-12)
    assert 2.0 - 0.03 <= pts[-1, 0] <= 2.0


@pytest.mark.parametrize(
    ("speed", "depth", "goal", "match"),
    [
        (0.0, 0.1, None, "speed"),
        (-1.0, 0.1, None, "speed"),
        (1.0, 0.0, None, "depth"),
        (1.0, 0.8, None, "deeper than the bed"),
        (1.0, 0.1, 0.9, "goal_height .* outside the bed"),
    ],
)
def test_bad_inputs_are_clear_errors(hill_bed, speed, depth, goal, match):
    config = load_config({"scenarios": {"hill": {"goal_height": goal}}} if goal else None)
    with pytest.raises(ValueError, match=match):
        plan_trajectory(hill_bed, speed, depth, config)


def test_missing_or_foreign_csv_is_refused(tmp_path):
    from dozerlab.runtime import DozerlabError

    with pytest.raises(DozerlabError, match="not found"):
        Trajectory.load_csv(tmp_path / "none.csv")
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    with pytest.raises(DozerlabError, match="header"):
        Trajectory.load_csv(tmp_path / "x.csv")


def test_plot_writes_png(step_bed, config, tmp_path):
    from dozerlab.scenarios.plots import plot_trajectory

    plot_trajectory(plan_trajectory(step_bed, 1.0, 0.1, config), tmp_path / "t.png")
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_trajectory_with_nan_is_never_written(hill_bed, config, tmp_path):
    traj = plan_trajectory(hill_bed, 0.7, 0.08, config)
    traj.position[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"t.csv: row 3 holds NaN/inf \('x'\)"):
        traj.save_csv(tmp_path / "t.csv")
    assert not (tmp_path / "t.csv").exists()
