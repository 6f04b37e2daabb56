"""The reduced run measured against NDEM: each figure on hand-made cases, and a run against
itself."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dozerlab.ndem.bodies import Bodies as NdemBodies
from dozerlab.reduce.compare import (
    compare_point,
    field_errors,
    height_accuracy,
    job_seconds,
    largest_overlap,
    outside_box,
    relative_l2,
    relative_rmse,
    sliced_emd,
    targets_met,
)
from dozerlab.reduce.projection import Bodies
from dozerlab.runtime import DozerlabError
from dozerlab.scenarios.bed import Bed


def test_height_accuracy_is_one_for_ndems_bed_and_zero_for_the_untouched_one():
    bed, ndem = np.zeros((4, 2)), np.full((4, 2), 0.1)
    assert height_accuracy(ndem, ndem, bed) == 1.0
    assert height_accuracy(bed, ndem, bed) == 0.0
    assert height_accuracy(np.full((4, 2), 0.05), ndem, bed) == pytest.approx(0.5)
    assert math.isnan(height_accuracy(ndem, bed, bed))  # NDEM changed nothing


def test_relative_errors():
    true = np.array([3.0, -4.0])
    assert relative_rmse(1.1 * true, true) == pytest.approx(0.1)
    assert relative_l2(true + [0.0, 1.0], true) == pytest.approx(1 / 5)
    assert math.isnan(relative_rmse(true, np.zeros(2))) and math.isnan(relative_l2(true, 0 * true))


def test_field_errors_per_row_weight_velocity_by_the_true_density():
    rho_true = np.array([[[[1.0, 3.0]]], [[[2.0, 2.0]]], [[[0.0, 0.0]]]])  # (3, 1, 1, 2)
    v_true = np.zeros((3, 1, 1, 2, 3))
    v_true[..., 0] = 1.0
    v = v_true.copy()
    v[1, 0, 0, 0, 0] = 3.0  # row 1: 2 m/s off in a bin of half the mass
    rho = rho_true.copy()
    rho[2] = 1.0  # row 2: mass where the truth has none
    ev, er = field_errors(v, rho, v_true, rho_true)
    # over the run's mean squared norms: velocity (4 + 4 + 0) / 3, density (10 + 8 + 0) / 3
    np.testing.assert_allclose(ev, [0.0, np.sqrt(2 * 4 / (8 / 3)), 0.0])
    np.testing.assert_allclose(er, [0.0, 0.0, np.sqrt(2 / 6)])
    nothing = field_errors(v, rho, v_true, 0 * rho_true)
    assert np.isnan(nothing[0]).all() and np.isnan(nothing[1]).all()  # no truth to compare with


def test_sliced_emd_sees_no_permutation_and_a_shift_at_most_its_length():
    cloud = np.random.default_rng(0).uniform(0, 1, (200, 3))
    assert sliced_emd(cloud, cloud[::-1]) == pytest.approx(0.0, abs=1e-15)
    shifted = sliced_emd(cloud, cloud + [0.1, 0.0, 0.0])
    # each projection moves by 0.1·d_x; |d_x| averages 1/2 over directions of the sphere
    assert 0.04 < shifted < 0.06
    assert sliced_emd(np.zeros((0, 3)), np.zeros((0, 3))) == 0.0
    with pytest.raises(ValueError, match="same shape"):
        sliced_emd(cloud, cloud[:10])


def test_validity_figures():
    pos = np.array([[0.0, 0.0, 0.5], [0.12, 0.0, 0.5], [2.0, 0.0, 0.5], [0.5, 0.6, -0.01]])
    radii = np.array([0.1, 0.05, 0.1, 0.1])
    assert largest_overlap(pos[:3], radii[:3]) == pytest.approx(0.03 / 0.05)  # of the smaller
    assert largest_overlap(pos[2:3], radii[2:3]) == 0.0
    assert outside_box(pos, 1.0, 1.0) == 2  # beyond x = 1 m; beyond y = 0.5 m and below ground


def test_body_penetration_is_the_deepest_overlap_with_a_body():
    from dozerlab.reduce.compare import body_penetration

    b = NdemBodies()
    b.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.5)
    bodies = Bodies(b.kind, b.center, b.rotations(), b.half, b.normal)
    pos = np.array([[0.0, 0.0, 0.07], [1.0, 0.0, 0.5]])
    assert body_penetration(pos, np.full(2, 0.1), bodies) == pytest.approx(0.03)
    assert body_penetration(pos[1:], np.full(1, 0.1), bodies) == 0.0


def test_job_seconds_read_snakemakes_benchmark(tmp_path):
    tsv = tmp_path / "b.tsv"
    tsv.write_text("s\th:m:s\tmax_rss\n12.5\t0:00:12\t100.0\n")
    assert job_seconds(tsv) == 12.5
    assert job_seconds(None) is None and job_seconds(tmp_path / "none.tsv") is None


def test_targets_met_and_missing_figures():
    targets = {
        "height_accuracy": 0.8,
        "force_rmse": 0.25,
        "loop_speedup": 50,
        "job_speedup": 5,
        "max_overlap": 0.1,
    }
    metrics = {
        "height_accuracy": 0.85,
        "force_x_rel_rmse": 0.3,
        "loop_speedup": 60.0,
        "job_speedup": None,
        "max_overlap_loop": float("nan"),
        "left_bed": 0,
        "body_depth_final_m": 2e-4,
    }
    assert targets_met(metrics, targets) == {
        "height_accuracy": True,
        "force_rmse": False,
        "loop_speedup": True,
        "job_speedup": None,
        "max_overlap": None,
        "nothing_left": True,
        "nothing_through": False,  # 0.2 mm into a body
    }
    # no deeper than NDEM's own final state of the point: its compliant contacts
    assert targets_met(metrics | {"body_depth_final_ndem_m": 3e-4}, targets)["nothing_through"]
    assert not targets_met(metrics | {"body_depth_final_ndem_m": 1e-4}, targets)["nothing_through"]


def test_a_run_against_itself_has_no_error(ndem_run):
    tmp, config = ndem_run
    store, bed, state = tmp / "ndem.zarr", tmp / "bed.npz", tmp / "ndem.npz"
    m, series = compare_point(store, store, bed, state, state, config)
    assert m["force_x_rel_rmse"] == 0.0 and m["velocity_rel_l2"] == 0.0
    assert m["density_rel_l2"] == 0.0 and m["final_emd_m"] == 0.0
    assert m["height_accuracy"] == 1.0 and m["loop_speedup"] == 1.0
    assert m["left_bed"] == m["left_bed_ndem"] and m["job_speedup"] is None
    assert series["force_ndem"].shape == (m["rows"], 3)
    np.testing.assert_array_equal(series["height_ndem"], series["height_reduced"])


def test_different_grain_counts_are_refused(ndem_run, tmp_path):
    tmp, config = ndem_run
    b = Bed.load(tmp / "bed.npz")
    keep = slice(0, b.count - 1)
    arrays = ("positions", "radii", "masses", "velocities", "angular_velocities")
    fewer = dataclasses.replace(b, **{k: getattr(b, k)[keep] for k in arrays})
    fewer.save(tmp_path / "fewer.npz")
    store = tmp / "ndem.zarr"
    with pytest.raises(DozerlabError, match="different grain counts"):
        compare_point(
            store, store, tmp / "bed.npz", tmp / "ndem.npz", tmp_path / "fewer.npz", config
        )


def test_gaussian_smooth_keeps_a_plane_and_spreads_a_spike():
    from dozerlab.reduce.compare import gaussian_smooth

    flat = np.full((20, 9), 0.3)
    np.testing.assert_allclose(gaussian_smooth(flat, 2.0), flat)
    spike = np.zeros((41, 41))
    spike[20, 20] = 1.0
    s = gaussian_smooth(spike, 3.0)
    assert s.sum() == pytest.approx(1.0) and s[20, 20] == pytest.approx(
        1 / (2 * np.pi * 9), rel=0.05
    )


def test_smoothed_surface_of_a_layer_is_its_top():
    from dozerlab.reduce.compare import smoothed_surface

    x, y = np.meshgrid(np.arange(0.05, 2.0, 0.1), np.arange(-0.45, 0.5, 0.1), indexing="ij")
    pos = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.05)], axis=1)
    h = smoothed_surface(pos, np.full(len(pos), 0.05), 2.0, 1.0, 0.1)
    assert h.shape == (80, 40)
    # a square lattice of touching spheres: between 0.05 (the gaps' rims) and 0.1 (their tops)
    assert 0.06 < h.mean() < 0.1 and h.max() - h.min() < 0.03


def test_low_pass_is_a_moving_mean():
    from dozerlab.reduce.compare import low_pass

    t = np.arange(200) * 0.01
    f = np.stack([np.sin(2 * np.pi * 10 * t) + 2.0, t], axis=1)  # 10 Hz ripple on a constant
    lp = low_pass(f, 0.01, 0.1)
    assert lp.shape == f.shape
    np.testing.assert_allclose(lp[10:-10, 0], 2.0, atol=1e-9)  # whole periods average out
    np.testing.assert_allclose(lp[10:-10, 1], t[10:-10] - 0.005, atol=1e-9)
