"""The reduced loop's step: advection by the field, frozen and ballistic grains."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from dozerlab.fields.sampling import SamplingGrid
from dozerlab.ndem.bodies import Bodies as NdemBodies
from dozerlab.reduce.compare import largest_overlap
from dozerlab.reduce.projection import Bodies
from dozerlab.reduce.simulation import ReducedSettings, ReducedState, density_correction


def _state(positions, velocities, grid, settings=None) -> ReducedState:
    """Grains of radius 0.02 m over the ground z = 0 and a blade box 0.1 × 1 × 1 m behind the tip."""
    b = NdemBodies()
    b.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.5)
    b.add_box((10.0, 0.0, 1.0), (0.05, 0.5, 0.5), True, 0.5, None)
    n = len(positions)
    return ReducedState(
        positions,
        velocities,
        np.full(n, 0.02),
        np.full(n, 0.1),
        Bodies(b.kind, b.center, b.rotations(), b.half, b.normal),
        np.array([0.05, 0.5, 0.5]),
        np.array([-0.05, 0.0, 0.5]),
        grid,
        np.array([0.0, 0.0, -9.81]),
        settings or ReducedSettings(),
        np.array([-1.0, -1.0, 0.0]),
        np.array([2.0, 1.0, 2.0]),
    )


def test_grains_in_the_volume_move_with_the_field_and_the_others_rest_or_fly():
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    tip = np.array([0.0, 0.0, 0.5])
    inside = np.array([[0.05, -0.15, 0.55], [0.2, 0.05, 0.7], [0.33, 0.12, 0.82]])
    resting, flying = [1.0, 0.5, 0.3], [1.4, -0.5, 1.5]
    x = np.vstack([inside, [resting, flying]])
    v = np.zeros_like(x)
    v[4] = [0.5, 0.0, 1.0]
    cx, cy, cz = np.meshgrid(*grid.centres(), indexing="ij")
    field = np.stack([0.3 + 0.5 * cx, -0.2 * cz, 0.1 + cy], -1)  # linear: interpolation exact
    h = 0.01
    state = _state(x, v, grid)
    state.step(field, np.full(grid.bins, 1500.0), tip, h)
    local = inside - tip  # the blade frame, as the bin centres
    expect_v = np.stack([0.3 + 0.5 * local[:, 0], -0.2 * local[:, 2], 0.1 + local[:, 1]], -1)
    np.testing.assert_allclose(state.x[:3], inside + h * expect_v, atol=1e-12)
    np.testing.assert_allclose(state.v[:3], expect_v, atol=1e-9)
    np.testing.assert_array_equal(state.x[3], resting)  # at rest outside: frozen
    fly_v = np.array([0.5, 0.0, 1.0 - 9.81 * h])
    np.testing.assert_allclose(state.x[4], np.array(flying) + h * fly_v, atol=1e-12)


def test_the_density_correction_moves_grains_down_the_excess_by_each_axis_bin():
    size, h, gain = (0.1, 0.2, 0.05), 0.02, 0.5
    field = np.full((5, 5, 5), 1000.0)
    assert not density_correction(field, field, size, h, gain, 2600.0).any()
    loop = field.copy()
    loop[2, 2, 2] += 260.0  # packed denser than the field by a tenth of the solid density
    v = density_correction(loop, field, size, h, gain, 2600.0)
    for a, length in enumerate(size):
        below, above = [2, 2, 2], [2, 2, 2]
        below[a], above[a] = 1, 3
        # out of the bin on either side: gain · L² / h times the central difference 0.1 / 2L
        out = gain * length * length / h * 0.1 / (2 * length)
        assert v[tuple(below)][a] == pytest.approx(-out)
        assert v[tuple(above)][a] == pytest.approx(out)
        assert not np.delete(v[tuple(below)], a).any()
    assert not v[2, 2, 2].any()
    np.testing.assert_allclose(density_correction(loop, field, size, h / 2, gain, 2600.0), 2 * v)
    # a bin the grains leave emptier than the field draws them in
    np.testing.assert_allclose(density_correction(field, loop, size, h, gain, 2600.0), -v)


def test_the_correction_moves_only_the_grains_the_field_carries():
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    tip = np.array([0.0, 0.0, 0.5])
    inside, resting = [0.2, 0.05, 0.7], [1.0, 0.5, 0.3]
    x = np.array([inside, resting])
    field = np.zeros((*grid.bins, 3))
    field[..., 0] = 0.3
    steer = np.zeros_like(field)
    steer[..., 2] = 0.2
    state = _state(x.copy(), np.zeros_like(x), grid)
    state.step(field, np.full(grid.bins, 1500.0), tip, 0.01, correction=steer)
    np.testing.assert_allclose(state.x[0], np.array(inside) + 0.01 * np.array([0.3, 0.0, 0.2]))
    np.testing.assert_allclose(state.v[0], [0.3, 0.0, 0.2])
    np.testing.assert_array_equal(state.x[1], resting)


def test_a_grain_at_rest_where_the_field_is_slower_than_the_rest_speed_stays_at_rest():
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    tip = np.array([0.0, 0.0, 0.5])
    x = np.array([[0.05, -0.15, 0.55], [0.35, 0.15, 0.85], [0.08, 0.1, 0.75]])
    v = np.zeros_like(x)
    v[2] = [0.1, 0.0, 0.0]  # moving already: the field carries it, however slowly
    cx, _, _ = np.meshgrid(*grid.centres(), indexing="ij")
    field = np.zeros((*grid.bins, 3))
    field[..., 0] = np.where(cx < 0.2, 0.04, 1.0)  # below the 0.05 m/s rest speed near the face
    state = _state(x, v, grid)
    state.step(field, np.full(grid.bins, 1500.0), tip, 0.01)
    np.testing.assert_array_equal(state.x[0], x[0])  # at rest in a slow field: stays
    assert not state.moving[0] and not state.v[0].any()
    np.testing.assert_allclose(state.x[1], x[1] + [0.01, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(state.x[2], x[2] + [0.0004, 0.0, 0.0], atol=1e-12)


def test_grains_above_the_volume_ride_with_its_top_and_fall_until_held_up():
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    above = np.array([[0.2, 0.0, 1.6]])  # over the volume (top 0.9 m) and its 2-bin margin
    field = np.zeros((*grid.bins, 3))
    field[..., 0] = 0.02  # slower than reduced.rest_speed
    field[..., 2] = 0.5  # the top bins rise: the grain above them does not
    h, g = 0.01, 9.81
    state = _state(above, np.zeros_like(above), grid)
    state.step(field, np.full(grid.bins, 1500.0), np.array([0.0, 0.0, 0.5]), h)
    np.testing.assert_allclose(state.x[0], above[0] + [h * 0.02, 0.0, -g * h * h], atol=1e-12)
    # the blade has moved on: the grain keeps falling, slow as it was
    for _ in range(3):
        state.step(field, np.full(grid.bins, 1500.0), np.array([5.0, 0.0, 0.5]), h)
    assert state.x[0, 2] == pytest.approx(above[0, 2] - 10 * g * h * h, rel=1e-9)  # 1+2+3+4

    # on a grain the field lifts, it is held up and carried along
    x = np.array([[0.2, 0.0, 0.8605], [0.2, 0.0, 0.9005]])
    state = _state(x, np.zeros_like(x), grid)
    for _ in range(2):
        state.step(field, np.full(grid.bins, 1500.0), np.array([0.0, 0.0, 0.5]), h)
    np.testing.assert_allclose(state.x[:, 0], 0.2 + 2 * h * 0.02, atol=1e-12)
    assert np.linalg.norm(state.x[1] - state.x[0]) == pytest.approx(0.04, abs=0.001)
    assert state.x[1, 2] > x[1, 2]


def test_the_piles_crest_rises_with_the_top_bins_up_to_crest_bins_above_the_volume():
    """Within reduced.crest_bins of the volume's top (0.9 m, bins of 0.1 m) a grain the top bins
    lift rises with them; higher up, or where they sink, it falls; crest_bins 0: all fall."""
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    tip = np.array([0.0, 0.0, 0.5])
    x = np.array([[0.2, -0.1, 0.95], [0.2, 0.1, 1.05]])  # half a bin and 1.5 bins above the top
    h, g = 0.01, 9.81
    for lift, crest, rising in ((0.5, 1.0, [True, False]), (-0.5, 1.0, [False, False])):
        field = np.zeros((*grid.bins, 3))
        field[..., 0], field[..., 2] = 1.0, lift
        for bins, expect in ((crest, rising), (0.0, [False, False])):
            state = _state(x, np.zeros_like(x), grid, ReducedSettings(crest_bins=bins))
            state.step(field, np.full(grid.bins, 1500.0), tip, h)
            vz = np.where(expect, lift, -g * h)
            np.testing.assert_allclose(state.x, x + h * np.c_[np.ones(2), np.zeros(2), vz])


def test_the_fields_edge_carries_grains_ahead_of_and_beside_the_volume():
    # one grain a bin ahead of the volume's front and one a bin beyond its side (past the
    # blade's end), both within reduced.advect_margin (2 bins), move with the edge bins; one
    # beyond the margin stays at rest (with nothing carried beside the volume, the ridge
    # model's loop lost 15 points of smoothed-surface accuracy: BENCHMARKS.md)
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    tip = np.array([0.0, 0.0, 0.5])
    x = np.array([[0.45, 0.0, 0.6], [0.2, 0.25, 0.6], [0.2, 0.45, 0.6]])
    field = np.zeros((*grid.bins, 3))
    field[..., 0], field[..., 2] = 1.0, 0.5
    h = 0.01
    state = _state(x, np.zeros_like(x), grid)
    state.step(field, np.full(grid.bins, 1500.0), tip, h)
    np.testing.assert_allclose(state.x[:2], x[:2] + h * np.array([1.0, 0.0, 0.5]), atol=1e-12)
    np.testing.assert_array_equal(state.x[2], x[2])


def test_no_pair_ends_a_step_overlapping_more_than_the_loop_reports():
    # A row of touching grains on the ground; the field drives the first, the only one in the
    # volume, one radius into the second. The third lies two selection cells from the first
    # (beyond the grains projected with it): pushed into by the second, it must hold as an
    # obstacle and count in the largest overlap.
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    x = np.array([[0.38 + 0.04 * i, 0.0, 0.02] for i in range(4)])
    field = np.zeros((*grid.bins, 3))
    field[..., 0] = 2.0
    state = _state(x, np.zeros_like(x), grid, ReducedSettings(advect_margin=0.0))
    stats = state.step(field, np.full(grid.bins, 1500.0), np.zeros(3), 0.01)
    assert not np.allclose(state.x, x)  # the step moved grains
    worst = largest_overlap(state.x, state.r)
    assert worst == pytest.approx(stats.max_overlap, abs=1e-12)
    assert worst <= 0.1


@pytest.mark.parametrize(("limit", "back"), [(10.0, False), (0.1, True)])
def test_a_grain_moved_past_the_ring_is_counted_over_the_whole_bed_or_goes_back(limit, back):
    # the field throws the grain 0.136 m (beyond the two selection cells of 0.05 m that the
    # projection reaches) onto a resting grain three cells away, 0.3 radius deep: counted over
    # the whole bed, it is the step's largest overlap; above overlap_limit the grain goes back
    # to where it started the step, without velocity
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    x = np.array([[0.30, 0.0, 0.02], [0.47, 0.0, 0.02]])
    field = np.zeros((*grid.bins, 3))
    field[..., 0] = 13.6
    settings = ReducedSettings(advect_margin=0.0, overlap_limit=limit)
    state = _state(x, np.zeros_like(x), grid, settings)
    stats = state.step(field, np.full(grid.bins, 1500.0), np.zeros(3), 0.01)
    assert state.beyond_ring == 1
    assert stats.max_overlap == pytest.approx(largest_overlap(state.x, state.r), abs=1e-12)
    if back:
        np.testing.assert_array_equal(state.x, x)
        np.testing.assert_array_equal(state.v, 0.0)
        assert stats.max_overlap == 0.0
    else:
        assert stats.max_overlap == pytest.approx(0.3, abs=1e-6)


def test_flow_is_the_fields_velocity_not_the_projections_push():
    # two grains in the volume driven head-on into a resting one outside it: the projection
    # stops them, but their flow stays what the field gave them; the pushed grain's flow is
    # its projected velocity
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    x = np.array([[0.30, 0.0, 0.02], [0.34, 0.0, 0.02], [0.38, 0.0, 0.02]])
    field = np.zeros((*grid.bins, 3))
    field[..., 0] = 2.0
    state = _state(x, np.zeros_like(x), grid, ReducedSettings(advect_margin=0.0))
    state.step(field, np.full(grid.bins, 1500.0), np.array([-0.05, 0.0, 0.0]), 0.01)
    np.testing.assert_allclose(state.flow[:2], [[2.0, 0.0, 0.0]] * 2, atol=1e-12)
    assert not np.allclose(state.v[:2], state.flow[:2])  # the projection changed their motion
    np.testing.assert_array_equal(state.flow[2], state.v[2])
    assert state.v[2, 0] > 0.0


@pytest.mark.parametrize(("angle", "rests"), [(45.0, False), (90.0, True)])
def test_a_falling_grain_rests_only_where_held_up_within_the_support_angle(angle, rests):
    # it lands on a resting grain 60° off the top: too steep a support at 45°, enough at 90°
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    below = np.array([1.0, 0.0, 0.02])
    off = np.radians(60.0)
    falling = below + 0.04 * np.array([np.sin(off), 0.0, np.cos(off)]) + [0.0, 0.0, 0.005]
    x = np.vstack([below, falling])
    v = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    state = _state(x, v, grid, ReducedSettings(support_angle=angle))
    state.step(np.zeros((*grid.bins, 3)), np.zeros(grid.bins), np.array([-5.0, 0.0, 0.5]), 0.01)
    assert np.linalg.norm(state.x[1] - state.x[0]) > 0.039  # pushed out of the grain below
    assert bool(state.moving[1]) is not rests
    assert bool(np.linalg.norm(state.v[1]) == 0.0) is rests

    # flat ground holds it at 45° too
    x = np.array([[1.0, 0.0, 0.025]])
    state = _state(x, np.array([[0.0, 0.0, -1.0]]), grid, ReducedSettings(support_angle=angle))
    state.step(np.zeros((*grid.bins, 3)), np.zeros(grid.bins), np.array([-5.0, 0.0, 0.5]), 0.01)
    assert not state.moving[0]
    assert state.x[0, 2] == pytest.approx(0.02)


def test_the_loop_reads_only_the_reduced_fields_the_workflow_passes_its_jobs():
    """The reduce rules pass only ``LOOP_FIELDS`` of the reduced section (so that the targets
    rerun the comparison alone): the loop's settings must not depend on any other field."""
    from dozerlab.config import load_config
    from dozerlab.reduce import LOOP_FIELDS

    changed = {
        "projection": {"method": "jacobi", "iterations": 7, "relaxation": 0.9, "tolerance": 0.1},
        "advect_margin": 1,
        "rest_speed": 0.2,
        "support_angle": 30,
        "divergence_overlap": 0.7,
        "density_models": ["ridge"],
        "density_gain": 0.2,
        "moved_radii": 3.0,
        "targets": {"force_skill": 0.9, "loop_speedup": 2},
        "twin": {"enabled": False, "jitter_m": 1e-5},
        "force_model": "mlp",
        "force_fields": "ndem",
        "dynamics_models": ["ridge"],
    }
    full = load_config({"reduced": changed})
    passed = load_config({"reduced": {k: v for k, v in changed.items() if k in LOOP_FIELDS}})
    assert ReducedSettings.from_config(passed) == ReducedSettings.from_config(full)
    assert ReducedSettings.from_config(full) != ReducedSettings.from_config(load_config({}))


def test_the_bed_at_rest_below_the_volume_holds_where_a_resting_grain_beside_it_yields():
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))  # z from 0.5 m up
    tip = np.array([0.0, 0.0, 0.5])
    carried = np.array([[0.15, 0.0, 0.53], [0.58, 0.1, 0.7]])  # in the volume, in its margin
    below, ahead = [0.15, 0.0, 0.49], [0.62, 0.1, 0.7]  # at rest, each touching one of them
    x = np.vstack([carried, [below, ahead]])
    field = np.broadcast_to(np.array([1.0, 0.0, -1.0]), (*grid.bins, 3)).copy()
    state = _state(x, np.zeros_like(x), grid)
    state.step(field, np.full(grid.bins, 1500.0), tip, 0.01)
    np.testing.assert_array_equal(state.x[2], below)  # held like the ground
    assert state.x[3, 0] > ahead[0] + 1e-3  # pushed ahead by the grain the field carried
    for a, b in ((0, 2), (1, 3)):
        assert np.linalg.norm(state.x[a] - state.x[b]) > 0.04 * (1 - 0.05 / 2) - 1e-9


@pytest.mark.parametrize(("limit", "freed"), [(10.0, False), (0.1, True)])
def test_a_grain_the_sweeps_leave_too_deep_goes_back_to_where_it_started(limit, freed):
    # the field drives a grain from above half a radius into one at rest below the volume
    # (held like the ground); with no sweeps (iterations 0) the overlap stays, as in a cage
    # of held grains the sweeps cannot open; overlap_limit 10: no second try
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))  # z from 0.1 m up
    tip = np.array([0.0, 0.0, 0.1])
    x = np.array([[0.2, 0.0, 0.02], [0.2, 0.0, 0.11]])
    field = np.broadcast_to(np.array([0.0, 0.0, -6.0]), (*grid.bins, 3)).copy()
    settings = ReducedSettings(iterations=0, overlap_limit=limit)
    state = _state(x, np.zeros_like(x), grid, settings)
    stats = state.step(field, np.full(grid.bins, 1500.0), tip, 0.01)
    worst = largest_overlap(state.x, state.r)
    assert worst == pytest.approx(stats.max_overlap, abs=1e-9)
    if freed:
        assert worst == 0.0
        np.testing.assert_array_equal(state.x, x)
    else:
        assert worst == pytest.approx(0.5)


def test_a_step_projected_again_sweeps_without_over_relaxation(monkeypatch):
    # the caged grain of the test above, over-relaxed sweeps asked for: the first projection
    # runs at the setting, the one after the grain went back at 1 (plain Gauss-Seidel: an
    # over-relaxed retry pushed grains of the default sweep's unet and persistence loops past
    # the ring, 0.70 and 0.92 radius deep over the whole bed, at 1.8 and 1.9)
    import dozerlab.reduce.simulation as simulation

    asked: list[float] = []

    def recorded(*args, **kwargs):
        asked.append(kwargs["relaxation"])
        return project(*args, **kwargs)

    project = simulation.project
    monkeypatch.setattr(simulation, "project", recorded)
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    x = np.array([[0.2, 0.0, 0.02], [0.2, 0.0, 0.11]])
    field = np.broadcast_to(np.array([0.0, 0.0, -6.0]), (*grid.bins, 3)).copy()
    settings = ReducedSettings(iterations=0, overlap_limit=0.1, relaxation=1.8)
    state = _state(x, np.zeros_like(x), grid, settings)
    state.step(field, np.full(grid.bins, 1500.0), np.array([0.0, 0.0, 0.1]), 0.01)
    assert asked == [1.8, 1.0]


def test_a_loops_settings_lift_the_crest_and_steer_only_for_the_models_named():
    settings = ReducedSettings(
        crest_bins=0.5, crest_models=("replay",), density_models=("ridge",), density_gain=0.5
    )
    assert settings.for_model("replay").crest_bins == 0.5
    assert settings.for_model("ridge") == dataclasses.replace(settings, crest_bins=0.0)
    assert settings.steers("ridge") and not settings.steers("replay")
    assert not dataclasses.replace(settings, density_gain=0.0).steers("ridge")


def test_compile_kernels_leaves_nothing_for_the_loop_to_compile_inside_its_clock(tmp_path):
    # a fresh process, as a reduce job: after compile_kernels (which steps and projects), NDEM's
    # sampled rows (one velocity a grain) and the loop's samplings (one velocity, or the
    # velocity and the flow) ask no kernel for a type it was not compiled for
    script = tmp_path / "loop.py"
    script.write_text(
        textwrap.dedent(
            """
            import numpy as np
            from numba.core.registry import CPUDispatcher

            from dozerlab.fields import sampling
            from dozerlab.fields.sampling import SamplingGrid
            from dozerlab.reduce import interpolate, projection, simulation

            def compiled():
                modules = (sampling, simulation, projection, interpolate)
                return {
                    (m.__name__, name): len(f.signatures)
                    for m in modules
                    for name, f in vars(m).items()
                    if isinstance(f, CPUDispatcher)
                }

            grid = SamplingGrid((4, 3, 2), (0.1, 0.1, 0.1), (0.0, -0.15, -0.05))
            simulation.compile_kernels(grid)
            before = compiled()
            rng = np.random.default_rng(0)
            x = rng.uniform([0.0, -0.1, 0.02], [0.4, 0.1, 0.2], (40, 3))
            v, r, m = rng.normal(size=(40, 3)), np.full(40, 0.02), np.full(40, 0.1)
            tip = np.zeros(3)
            grid.sample(x, v, r, m, tip)
            grid.sample_velocities(x, (v,), r, m, tip)
            grid.sample_velocities(x, (v, v), r, m, tip)
            after = compiled()
            new = {k: after[k] - before[k] for k in after if after[k] != before[k]}
            print("new signatures:", new)
            """
        )
    )
    out = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, check=True, timeout=600
    )
    assert "new signatures: {}" in out.stdout, out.stdout + out.stderr
