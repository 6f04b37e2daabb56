"""The evolution models' figures: marked PNGs, and no foreign file replaced."""

import numpy as np
import pytest

from dozerlab.learn.dynamics.plots import density_slices, rollout_curves
from dozerlab.runtime import FIGURE, OutputExistsError


def test_curves_and_slices_are_written_as_dozerlab_figures(tmp_path):
    curve = {
        "velocity": [0.1, 0.2, 0.4],
        "density": [0.05, 0.1, 0.2],
        "mass_ratio": [1.0, 1.01, 1.03],
    }
    out = rollout_curves({"ridge": curve, "persistence": curve}, tmp_path / "r.png", "hill")
    assert out == tmp_path / "r.png" and FIGURE.recognise(out)
    fields = np.random.default_rng(0).uniform(0, 1500, (2, 5, 6, 3, 4))
    slices = density_slices(fields, [1, 5], tmp_path / "s.png", "hill")
    assert FIGURE.recognise(slices)


def test_a_foreign_file_at_the_path_is_left_alone(tmp_path):
    mine = tmp_path / "r.png"
    mine.write_text("my figure")
    curve = {"velocity": [0.1], "density": [0.1], "mass_ratio": [1.0]}
    with pytest.raises(OutputExistsError):
        rollout_curves({"ridge": curve}, mine)
    assert mine.read_text() == "my figure"
