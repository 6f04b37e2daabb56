"""The scenarios layer's jobs: what they write, and the refusals that come before any work."""

import numpy as np
import pytest

from dozerlab.runtime import ConfigError, OutputExistsError
from dozerlab.scenarios.jobs import bed_job, trajectory_job
from dozerlab.scenarios.trajectory import Trajectory, plan_trajectory


def test_trajectory_job_saves_the_planned_path(hill_bed, config, tmp_path):
    hill_bed.save(tmp_path / "hill.npz")
    out = tmp_path / "speed~1.0_depth~0.1.csv"
    traj = trajectory_job(tmp_path / "hill.npz", 1.0, 0.1, config, out)
    expected = plan_trajectory(hill_bed, 1.0, 0.1, config)
    saved = Trajectory.load_csv(out)
    np.testing.assert_allclose(saved.position, expected.position)
    np.testing.assert_allclose(traj.velocity, expected.velocity)


def test_trajectory_job_refuses_a_foreign_plot_before_writing(hill_bed, config, tmp_path):
    hill_bed.save(tmp_path / "hill.npz")
    plot = tmp_path / "mine.png"
    plot.write_bytes(b"\x89PNG my own figure")
    out = tmp_path / "t.csv"
    with pytest.raises(OutputExistsError, match=r"mine\.png"):
        trajectory_job(tmp_path / "hill.npz", 1.0, 0.1, config, out, plot=plot)
    assert not out.exists() and plot.read_bytes() == b"\x89PNG my own figure"


def test_bed_job_refuses_before_settling(config, tmp_path):
    with pytest.raises(
        ConfigError,
        match=r"--scenario 'dune' is not defined \(allowed: one of \['hill', 'step', 'trench'\]",
    ):
        bed_job("dune", config, tmp_path / "b.npz")
    out = tmp_path / "b.npz"
    out.write_text("not a bed")
    with pytest.raises(OutputExistsError, match=r"b\.npz"):
        bed_job("hill", config, out)
    assert out.read_text() == "not a bed"
