"""The reduced run measured against NDEM: each figure on hand-made cases, and a run against
itself."""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest

from dozerlab.ndem.bodies import Bodies as NdemBodies
from dozerlab.reduce.compare import (
    EXPECTED_FIGURES,
    FIGURES,
    against_expected,
    compare_point,
    field_errors,
    gaussian_smooth,
    height_accuracy,
    job_seconds,
    job_shares,
    largest_overlap,
    low_pass,
    outside_box,
    relative_l2,
    relative_rmse,
    skills,
    sliced_emd,
    smoothed_surface,
    surface_errors,
    surface_regions,
    targets_met,
    transfer_gap,
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


def test_each_point_of_a_job_takes_its_loop_and_an_equal_part_of_the_rest():
    # a 12 s job of loops of 2, 3 and 4 s: the 3 s left (start-up, models, writing) split three ways
    assert job_shares(12.0, [2.0, 3.0, 4.0]) == pytest.approx([3.0, 4.0, 5.0])
    assert sum(job_shares(12.0, [2.0, 3.0, 4.0])) == pytest.approx(12.0)
    assert job_shares(7.0, [4.0]) == [7.0]  # one point: the whole job
    assert job_shares(None, [2.0, 3.0]) == [None, None]
    assert job_shares(12.0, [2.0, None]) == [None, None]
    with pytest.raises(DozerlabError, match="shorter than its 2 loops"):
        job_shares(4.0, [2.0, 3.0])  # the record of another job


TARGETS = {
    "replay_surface_skill": 0.95,
    "surface_skill": 0.9,
    "force_skill": 0.8,
    "loop_speedup": 40,
    "job_speedup": 10,
    "max_overlap": 0.1,
}


def test_targets_met_and_missing_figures():
    metrics = {
        "surface_accuracy_skill": 0.92,
        "force_lp_rel_rmse_skill": 0.85,
        "loop_speedup": 60.0,
        "job_speedup": None,
        "max_overlap_loop": float("nan"),
        "left_bed": 0,
        "body_depth_final_m": 2e-4,
    }
    assert targets_met(metrics, TARGETS) == {
        "surface_skill": True,
        "force_skill": False,  # 0.85 of the twin's error, above 0.8
        "loop_speedup": True,
        "job_speedup": None,
        "max_overlap": None,
        "nothing_left": True,
        "nothing_through": False,  # 0.2 mm into a body
    }
    # replay, the loop's own fidelity, is held to the surface skill of 0.95 alone
    replay = targets_met(metrics, TARGETS, replay=True)
    assert replay["replay_surface_skill"] is False
    assert "surface_skill" not in replay and "force_skill" not in replay
    # without a twin there is no skill: not met, not missed
    bare = {k: v for k, v in metrics.items() if not k.endswith("_skill")}
    assert targets_met(bare, TARGETS)["surface_skill"] is None
    assert targets_met(bare, TARGETS)["force_skill"] is None
    # no deeper than NDEM's own final state of the point: its compliant contacts
    assert targets_met(metrics | {"body_depth_final_ndem_m": 3e-4}, TARGETS)["nothing_through"]
    assert not targets_met(metrics | {"body_depth_final_ndem_m": 1e-4}, TARGETS)["nothing_through"]


def test_skills_are_each_figure_over_the_twins():
    run = {"surface_accuracy": 0.72, "force_lp_rel_rmse": 0.08, "final_emd_m": 0.02}
    twin = {"surface_accuracy": 0.9, "force_lp_rel_rmse": 0.1, "final_emd_m": 0.0}
    got = skills(run, twin)
    assert set(got) == {f"{k}_skill" for k in FIGURES}
    assert got["surface_accuracy_skill"] == pytest.approx(0.8)
    assert got["force_lp_rel_rmse_skill"] == pytest.approx(0.8)
    assert got["final_emd_m_skill"] is None  # the twin's is 0: no ratio
    assert got["height_accuracy_skill"] is None  # measured by neither


def test_gaussian_smoothing_keeps_a_plane_and_spreads_a_step_over_sigma():
    plane = np.full((40, 10), 0.3)
    np.testing.assert_allclose(gaussian_smooth(plane, 3.0), plane)  # edges extended: no sag
    step = np.zeros((60, 4))
    step[30:] = 1.0
    smooth = gaussian_smooth(step, 4.0)
    np.testing.assert_allclose(smooth[:, 0], smooth[:, 3])  # along x only
    assert smooth[0, 0] == pytest.approx(0.0) and smooth[-1, 0] == pytest.approx(1.0)
    # the step sits between cells 29 and 30: half its height there, Φ(±1) one σ away
    assert (smooth[29, 0] + smooth[30, 0]) / 2 == pytest.approx(0.5, abs=1e-9)
    assert smooth[34, 0] == pytest.approx(0.5 * (1 + math.erf(4.5 / 4 / math.sqrt(2))), abs=0.01)
    np.testing.assert_array_equal(gaussian_smooth(step, 0.0), step)


def _layer(dz: float = 0.0, dx: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """One layer of spheres (r 0.05 m) on a 0.05 m lattice over a 2 m × 1 m bed (overlapping:
    no cell between them is bare ground), shifted."""
    x, y = np.meshgrid(np.arange(0.025, 2.0, 0.05), np.arange(-0.475, 0.5, 0.05), indexing="ij")
    pos = np.column_stack([x.ravel() + dx, y.ravel(), np.full(x.size, 0.05 + dz)])
    return pos, np.full(len(pos), 0.05)


def test_the_smoothed_surface_follows_a_lift_exactly_and_hides_the_grain_scale():
    pos, radii = _layer()
    base = smoothed_surface(pos, radii, 2.0, 1.0, sigma=0.1)
    assert base.shape == (80, 40)  # cells of σ/4
    np.testing.assert_allclose(smoothed_surface(*_layer(dz=0.02), 2.0, 1.0, 0.1), base + 0.02)
    # the spheres' bumps (15 mm) all but vanish at σ = one diameter
    raw = smoothed_surface(pos, radii, 2.0, 1.0, sigma=0.004)
    assert np.ptp(raw) > 0.01 and np.ptp(base) < 0.1 * np.ptp(raw)


def test_surface_accuracy_of_surfaces_shifted_by_known_amounts():
    """A run that lifts the bed 30 mm against NDEM's 40 mm is 75 % accurate; one that lifts it
    50 mm, 75 % too; one that moves nothing, 0."""
    bed = smoothed_surface(*_layer(), 2.0, 1.0, 0.1)
    ndem = smoothed_surface(*_layer(dz=0.04), 2.0, 1.0, 0.1)
    for dz, accuracy in ((0.04, 1.0), (0.03, 0.75), (0.05, 0.75), (0.0, 0.0)):
        run = smoothed_surface(*_layer(dz=dz), 2.0, 1.0, 0.1)
        assert height_accuracy(run, ndem, bed) == pytest.approx(accuracy, abs=1e-9)


def test_surface_regions_split_the_bed_at_the_blades_last_tip_and_its_swath():
    """A 4 m × 1 m bed of 0.1 m cells, a 0.4 m blade driven along y = 0.1 to x = 2.5 m."""
    path = np.column_stack([np.linspace(0.0, 2.5, 26), np.full(26, 0.1), np.zeros(26)])
    r = surface_regions((40, 10), 4.0, 1.0, path, 0.4)
    x = (np.arange(40) + 0.5) * 0.1
    y = (np.arange(10) + 0.5) * 0.1 - 0.5
    assert set(r) == {"swath", "beside", "ahead"}
    total = sum(m.astype(int) for m in r.values())
    np.testing.assert_array_equal(total, 1)  # every cell in exactly one region
    np.testing.assert_array_equal(r["ahead"], np.broadcast_to((x >= 2.5)[:, None], (40, 10)))
    # behind the tip, the swath is |y − 0.1| < 0.2: the cells at y = -0.05 … 0.25
    inside = np.abs(y - 0.1) < 0.2
    np.testing.assert_array_equal(r["swath"][x < 2.5], np.broadcast_to(inside, (25, 10)))
    assert r["swath"][x < 2.5].sum(axis=1).tolist() == [4] * 25


def test_surface_errors_say_where_the_error_lies_and_add_up_to_the_accuracy():
    """NDEM lifts the whole bed 40 mm; the run lifts it 40 mm but for the strips beside the swath,
    where it lifts 20 mm, and ahead, where it lifts 50 mm."""
    path = np.column_stack([np.linspace(0.0, 1.0, 11), np.zeros(11), np.zeros(11)])
    r = surface_regions((20, 10), 2.0, 1.0, path, 0.4)
    bed = np.zeros((20, 10))
    ndem = bed + 0.04
    run = ndem.copy()
    run[r["beside"]] = 0.02
    run[r["ahead"]] = 0.05
    e = surface_errors(run, ndem, bed, r)
    n = 200.0 * 0.04  # NDEM's change over the bed
    assert e["surface_error_swath"] == 0.0 and e["surface_excess_swath"] == 0.0
    assert e["surface_error_beside"] == pytest.approx(r["beside"].sum() * 0.02 / n)
    assert e["surface_excess_beside"] == pytest.approx(-e["surface_error_beside"])
    assert e["surface_excess_ahead"] == pytest.approx(100 * 0.01 / n)
    errors = sum(e[f"surface_error_{k}"] for k in r)
    assert 1.0 - errors == pytest.approx(height_accuracy(run, ndem, bed))
    assert all(math.isnan(v) for v in surface_errors(run, bed, bed, r).values())


def test_low_passed_forces_that_differ_only_faster_than_the_window_agree():
    dt, t = 0.01, np.arange(300) * 0.01
    force = 2.0 + np.sin(2 * np.pi * t / 2.0)  # a 2 s swell
    chatter = force + 0.5 * np.sin(2 * np.pi * t / 0.05)  # plus a 0.05 s chatter
    assert relative_rmse(chatter, force) > 0.1
    lp, lp_ref = low_pass(chatter, dt, 0.1), low_pass(force, dt, 0.1)
    # whole periods of the chatter in every full window (the ends average what they hold)
    assert relative_rmse(lp[5:-5], lp_ref[5:-5]) < 1e-12
    # a 0.1 s period averaged over a 0.1 s window leaves its mean
    np.testing.assert_allclose(low_pass(2 + np.sin(20 * np.pi * t), dt, 0.1)[5:-5], 2.0, atol=1e-12)


def test_a_run_against_itself_has_no_error(ndem_run):
    tmp, config = ndem_run
    store, bed, state = tmp / "ndem.zarr", tmp / "bed.npz", tmp / "ndem.npz"
    m, series = compare_point(store, store, bed, state, state, config, twin=(store, state))
    assert m["force_x_rel_rmse"] == 0.0 and m["velocity_rel_l2"] == 0.0
    assert m["density_rel_l2"] == 0.0 and m["final_emd_m"] == 0.0
    assert m["force_lp_rel_rmse"] == 0.0 and m["force_mean_rel_err"] == 0.0
    assert m["height_accuracy"] == 1.0 and m["surface_accuracy"] == 1.0
    regions = ("swath", "beside", "ahead")
    assert all(m[f"surface_{w}_{r}"] == 0.0 for w in ("error", "excess") for r in regions)
    assert series["surface_reduced"].shape == series["surface_ndem"].shape
    assert m["loop_speedup"] == 1.0
    assert m["left_bed"] == m["left_bed_ndem"] and m["job_speedup"] is None
    assert series["force_ndem"].shape == (m["rows"], 3)
    np.testing.assert_array_equal(series["height_ndem"], series["height_reduced"])
    # the "twin" is NDEM too: its figures are the run's, accuracy skills 1, errors 0 over 0 none
    assert all(m[f"twin_{k}"] == m[k] for k in FIGURES)
    assert m["surface_accuracy_skill"] == 1.0 and m["height_accuracy_skill"] == 1.0
    assert m["force_lp_rel_rmse_skill"] is None
    np.testing.assert_array_equal(series["force_twin"], series["force_ndem"])
    bare, _ = compare_point(store, store, bed, state, state, config)
    assert not any(k.startswith("twin_") or k.endswith("_skill") for k in bare)


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


def test_transfer_gap_sets_unseen_terrain_against_the_seen_shapes():
    entries = [
        {"role": "interpolation", "surface_accuracy_skill": 0.78},
        {"role": "extrapolation", "surface_accuracy_skill": 0.74},
        {"role": "extrapolation", "surface_accuracy_skill": None},  # no twin: left out
        {"role": "transfer", "surface_accuracy_skill": 0.54},
    ]
    gap = transfer_gap(entries, 0.1)
    assert gap is not None
    assert gap["surface_skill_seen"] == pytest.approx(0.76)
    assert gap["gap"] == pytest.approx(-0.22) and gap["met"] is False
    entries[-1]["surface_accuracy_skill"] = 0.70
    assert transfer_gap(entries, 0.1)["met"] is True  # type: ignore[index]
    assert transfer_gap(entries[:3], 0.1) is None  # no unseen terrain


def test_the_expected_run_is_the_mean_of_the_draws():
    """Two draws whose forces are 1.1 and 1.3 times a swell and whose surfaces rise 30 and 50 mm:
    the expected run is 1.2 times the swell and 40 mm, so a run that is it scores no error and
    full accuracy, and NDEM's run (the swell, the bed 20 mm up) misses by a sixth and by half."""
    dt, t = 0.01, np.arange(300) * 0.01
    swell = np.zeros((300, 3))
    swell[:, 0] = 2.0 + np.sin(2 * np.pi * t / 2.0)
    bed = smoothed_surface(*_layer(), 2.0, 1.0, 0.1)
    ref = types.SimpleNamespace(surface_bed=bed, row_dt=dt)
    draws = [
        {"force": k * swell, "surface": smoothed_surface(*_layer(dz=dz), 2.0, 1.0, 0.1)}
        for k, dz in ((1.1, 0.03), (1.3, 0.05))
    ]
    rows = slice(10, None)
    mean = against_expected(
        ref, 1.2 * swell, smoothed_surface(*_layer(dz=0.04), 2.0, 1.0, 0.1), draws, rows
    )
    assert mean["force_lp_rel_rmse"] == pytest.approx(0.0, abs=1e-12)
    assert mean["surface_accuracy"] == pytest.approx(1.0, abs=1e-9)
    ndem = against_expected(
        ref, swell, smoothed_surface(*_layer(dz=0.02), 2.0, 1.0, 0.1), draws, rows
    )
    assert ndem["force_lp_rel_rmse"] == pytest.approx(0.2 / 1.2, rel=1e-9)
    assert ndem["surface_accuracy"] == pytest.approx(0.5, abs=1e-9)
    assert set(mean) == set(EXPECTED_FIGURES)
    with pytest.raises(ValueError, match="at least one draw"):
        against_expected(ref, swell, bed, [], rows)


def test_twin_draws_average_the_twin_and_measure_the_expected_run(ndem_run):
    """With NDEM itself as the run, the twin and two more draws, the twin's figures are NDEM's,
    the run and NDEM's run both are the expected run (no error, full accuracy) and the force
    skill has no denominator; draws without the twin are refused."""
    tmp, config = ndem_run
    store, bed, state = tmp / "ndem.zarr", tmp / "bed.npz", tmp / "ndem.npz"
    one, _ = compare_point(store, store, bed, state, state, config, twin=(store, state))
    m, _ = compare_point(
        store, store, bed, state, state, config, twin=(store, state), draws=[(store, state)] * 2
    )
    assert m["twin_draws"] == 3 and "twin_draws" not in one
    assert all(m[f"twin_{k}"] == pytest.approx(one[f"twin_{k}"]) for k in FIGURES)
    assert m["expected_force_lp_rel_rmse"] == 0.0 and m["ndem_expected_force_lp_rel_rmse"] == 0.0
    assert m["expected_surface_accuracy"] == 1.0 and m["expected_surface_accuracy_skill"] == 1.0
    assert m["expected_force_lp_rel_rmse_skill"] is None
    with pytest.raises(ValueError, match="need the twin"):
        compare_point(store, store, bed, state, state, config, draws=[(store, state)])
