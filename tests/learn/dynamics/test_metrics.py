"""The evolution models' errors: ratios of sums, mass along the rollout, aggregation."""

import math

import numpy as np
import pytest
import torch

from dozerlab.learn.dynamics.metrics import (
    combine,
    error_sums,
    evaluate_store,
    public,
    ratios,
    summarize,
)
from dozerlab.learn.dynamics.models import DynamicsModel

from .helpers import BIN, DT, GRID, steady


def test_error_sums_weight_the_velocity_by_the_true_density():
    # two bins: ρ_true 1 and 3 kg/m³, v_true (1, 0, 0) and (0, 2, 0) m/s; the prediction is off
    # by 0.5 m/s along x in both and by 1 kg/m³ in the first
    rho_true = torch.tensor([1.0, 3.0]).view(1, 1, 2)
    v_true = torch.tensor([[1.0, 0, 0], [0, 2.0, 0]]).view(1, 1, 2, 3)
    sums = error_sums(
        v_true + torch.tensor([0.5, 0, 0]),
        rho_true + torch.tensor([1.0, 0]).view(1, 1, 2),
        v_true,
        rho_true,
    )
    np.testing.assert_allclose(sums, [1 * 0.25 + 3 * 0.25, 1 * 1 + 3 * 4, 1.0, 1 + 9])
    r = ratios(sums)
    assert r == pytest.approx({"velocity": math.sqrt(1 / 13), "density": math.sqrt(1 / 10)})
    assert all(math.isnan(v) for v in ratios(np.zeros(4)).values())


def test_summary_reads_reported_steps_at_the_runs_end_and_the_worst_mass():
    sums = np.array([[1.0, 4.0, 1.0, 100.0], [4.0, 4.0, 4.0, 100.0], [9.0, 4.0, 9.0, 100.0]])
    mass = np.array([[1.0, 1.1, 1.2], [1.0, 0.9, 1.0]])
    out = summarize(np.array([1.0, 100.0, 0.0, 1.0]), sums, mass, np.ones((2, 3)))
    assert out["one_step"] == {"velocity": 0.1, "density": 0.0}
    assert out["rollout"]["velocity"] == [0.5, 1.0, 1.5]
    assert (
        out["rollout_at"]["10"]
        == out["rollout_at"]["100"]
        == {
            "steps": 3,
            "velocity": 1.5,
            "density": 0.3,
        }
    )
    assert out["rollout"]["mass_ratio"] == pytest.approx([1.0, 1.0, 1.1])
    assert out["mass"]["max_abs_error"] == pytest.approx(0.1)  # of the summed masses
    assert out["mass"]["worst_rollout_error"] == pytest.approx(0.2)  # of one rollout


def test_persistence_on_a_steady_field_is_exact_and_points_combine():
    model = DynamicsModel("persistence", GRID, 2, 1, DT, BIN)
    a = evaluate_store(model, steady(20), steps=5, starts=3)
    b = evaluate_store(model, steady(12), steps=15, starts=2)
    assert a["one_step"]["velocity"] == 0.0 and a["one_step"]["density"] == 0.0
    assert len(a["rollout"]["velocity"]) == 5 and len(b["rollout"]["velocity"]) == 10  # 12 − 2
    assert a["starts"] == [1, 8, 14] and a["rows"] == 20
    overall = combine([a, b])
    assert len(overall["rollout"]["velocity"]) == 10
    assert overall["mass"]["max_abs_error"] == 0.0
    assert set(public(a)) == set(a) - {"_sums", "_rollout"}
