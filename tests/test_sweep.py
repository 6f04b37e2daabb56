"""The sweep's vocabulary: canonical numbers, points and their roles, result paths."""

import re

import pytest

from dozerlab import sweep as P
from dozerlab.config import ConfigError, load_config
from tests.helpers import SMALL_SWEEP

CFG = load_config(SMALL_SWEEP)


@pytest.mark.parametrize(
    ("value", "text"), [(1.0, "1.0"), (0.1, "0.1"), (0.05, "0.05"), (1e-5, "0.00001"), (20, "20.0")]
)
def test_numbers_round_trip(value, text):
    assert P.fmt_number(value) == text
    assert P.check_canonical("speed", text) == pytest.approx(value)
    assert re.fullmatch(P.NUMBER_PATTERN, text)


@pytest.mark.parametrize("text", ["1", "1.00", "01.0"])
def test_non_canonical_spelling_names_the_canonical_one(text):
    with pytest.raises(ValueError, match=r"speed~1\.0"):
        P.check_canonical("speed", text)


def test_sweep_points_and_paths():
    pts = P.sweep_points(CFG)
    assert [(p.role, p.name) for p in pts] == [
        ("train", "speed~0.5_depth~0.1"),
        ("train", "speed~1.0_depth~0.1"),
        ("interpolation", "speed~0.75_depth~0.1"),
        ("extrapolation", "speed~2.0_depth~0.1"),
    ]
    assert str(P.field_path("results", pts[1])) == "results/fields/hill/speed~1.0_depth~0.1.zarr"
    assert (
        str(P.trajectory_path("results", pts[1], "png"))
        == "results/trajectories/hill/speed~1.0_depth~0.1.png"
    )
    back = P.parse_point("results/fields/hill/speed~1.0_depth~0.1.zarr")
    assert (back.scenario, back.speed, back.depth) == ("hill", 1.0, 0.1)


def test_held_out_point_on_the_grid_is_refused():
    cfg = load_config({"sweep": {"speeds": [1.0], "depths": [0.1]}})
    cfg["sweep"]["extrapolation"] = [{"scenario": "step", "speed": 1.0, "depth": 0.1}]
    with pytest.raises(ConfigError, match=r"sweep\.extrapolation\[0\]"):
        P.sweep_points(cfg)
    with pytest.raises(ConfigError, match=r"sweep\.extrapolation\[0\]"):
        load_config(cfg)  # and the config is refused before anything runs


def test_roles_and_the_paths_of_beds_models_and_validation():
    pts = P.sweep_points(CFG)
    assert [p.name for p in P.by_role(pts, "interpolation")] == ["speed~0.75_depth~0.1"]
    assert P.by_role(pts, "train")[0].key == ("hill", "speed~0.5_depth~0.1")
    with pytest.raises(ValueError, match="role must be one of"):
        P.by_role(pts, "test")
    assert str(P.bed_path("results", "hill")) == "results/beds/hill.npz"
    assert str(P.model_path("results", "unet")) == "results/models/unet"
    assert str(P.validation_path("results", "unet")) == "results/validation/unet.json"
    assert (
        str(P.simulate_benchmark_path("results", pts[0]))
        == "results/benchmarks/simulate/hill/speed~0.5_depth~0.1.tsv"
    )


def test_a_loop_fitted_force_model_serves_its_own_dynamics_model_and_replay_the_ndem_one():
    loop = {"force_fields": "loop", "force_model": "linear"}
    assert str(P.reduce_force_model_path("results", loop, "ridge")) == (
        "results/reduced/ridge/force_model"
    )
    assert str(P.reduce_force_model_path("results", loop, "replay")) == "results/models/linear"
    ndem = {"force_fields": "ndem", "force_model": "unet"}
    assert str(P.reduce_force_model_path("results", ndem, "ridge")) == "results/models/unet"


def test_the_twin_is_draw_one_and_further_draws_are_named_by_number():
    point = P.sweep_points(CFG)[2]
    assert [tuple(map(str, run)) for run in P.twin_draws("results", point, 2)] == [
        (
            "results/twins/hill/speed~0.75_depth~0.1.zarr",
            "results/twins/hill/speed~0.75_depth~0.1.npz",
        ),
        (
            "results/twins/hill/speed~0.75_depth~0.1_draw~2.zarr",
            "results/twins/hill/speed~0.75_depth~0.1_draw~2.npz",
        ),
    ]
    assert P.twin_path("results", point, "zarr", 1) == P.twin_path("results", point)
    with pytest.raises(ValueError, match="count from 1"):
        P.twin_path("results", point, draw=0)


@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf")])
def test_negative_and_non_finite_numbers_are_refused(value):
    with pytest.raises(ValueError, match="finite and >= 0"):
        P.fmt_number(value)


@pytest.mark.parametrize("name", ["speed~1_depth~0.1.zarr", "run.zarr", "speed~1.0.zarr"])
def test_a_path_not_named_after_a_point_is_refused(name):
    with pytest.raises(ValueError, match="is not named"):
        P.parse_point(f"results/fields/hill/{name}")


def test_a_point_listed_twice_among_held_out_points_is_refused():
    twice = {"scenario": "hill", "speed": 0.75, "depth": 0.1}
    cfg = load_config({"sweep": {"speeds": [1.0], "depths": [0.1]}})
    cfg["sweep"]["interpolation"] = [twice] * 2
    message = r"sweep\.interpolation\[1\].*already in the sweep\.interpolation"
    with pytest.raises(ConfigError, match=message):
        P.sweep_points(cfg)
    with pytest.raises(ConfigError, match=message):
        load_config(cfg)  # and the config is refused before anything runs
