"""Terrain from the config: presets, profiles and heightmaps give the target height, and every
terrain that cannot be built is refused before any job, naming its field."""

from pathlib import Path

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.runtime import ConfigError
from dozerlab.terrain import PRESETS, lowest_level, target_height

BED = {"length": 2.0, "width": 0.5, "radius": 0.025}
RAMP = {"kind": "profile", "points": [[0.0, 0.2], [1.0, 0.4], [2.0, 0.4]], "goal_height": 0.25}


def config_with(scenario: dict, name: str = "site", **sweep) -> dict:
    doc = {"bed": BED, "scenarios": {name: scenario}}
    if sweep:
        doc["sweep"] = sweep
    return doc


def test_a_profile_is_linear_between_its_points_and_held_beyond_them():
    cfg = load_config(config_with({**RAMP, "points": [[0.5, 0.2], [1.5, 0.4]]}))
    x = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    np.testing.assert_allclose(target_height("site", cfg, x), [0.2, 0.2, 0.3, 0.4, 0.4])
    # constant across the width
    np.testing.assert_allclose(target_height("site", cfg, 1.0, np.array([-0.25, 0.25])), 0.3)
    assert lowest_level("site", cfg) == ("scenarios.site.points", 0.2)


@pytest.mark.parametrize("suffix", [".npy", ".csv"])
def test_a_heightmap_spans_the_ground_corner_to_corner_and_is_bilinear(tmp_path, suffix):
    z = np.array([[0.1, 0.3], [0.2, 0.4], [0.3, 0.5]])  # rows along x, columns along y
    path = tmp_path / f"site{suffix}"
    if suffix == ".npy":
        np.save(path, z)
    else:
        np.savetxt(path, z, delimiter=",")
    cfg = load_config(config_with({"kind": "heightmap", "file": str(path)}))
    corners = target_height(
        "site", cfg, np.array([0.0, 0.0, 2.0, 2.0]), np.array([-0.25, 0.25, -0.25, 0.25])
    )
    np.testing.assert_allclose(corners, [0.1, 0.3, 0.3, 0.5])
    # the middle of the first cell: the mean of its four corners; outside the ground: clamped
    np.testing.assert_allclose(target_height("site", cfg, 0.5, 0.0), 0.25)
    np.testing.assert_allclose(target_height("site", cfg, 3.0, 1.0), 0.5)
    assert lowest_level("site", cfg) == ("scenarios.site.file", 0.1)


def test_the_presets_are_named_scenarios_and_the_trench_dips():
    cfg = load_config({"bed": BED})
    assert set(PRESETS) <= set(cfg["scenarios"])
    t = cfg["scenarios"]["trench"]
    x = np.linspace(0.0, 2.0, 201)
    h = target_height("trench", cfg, x)
    assert h.min() == pytest.approx(t["bottom_height"])
    assert x[np.argmin(h)] == pytest.approx(t["center"] * BED["length"])
    assert h[0] == h[-1] == pytest.approx(t["base_height"])


def write_npy(tmp_path: Path, array: np.ndarray) -> str:
    np.save(tmp_path / "map.npy", array)
    return str(tmp_path / "map.npy")


@pytest.mark.parametrize(
    ("scenario", "field", "message"),
    [
        (
            {**RAMP, "points": [[0.0, 0.2], [1.0, 0.3], [0.5, 0.3]]},
            "scenarios.site.points[2]",
            "sorted by x",
        ),
        (
            {**RAMP, "points": [[0.0, 0.2], [1.0, 0.3], [1.0, 0.4]]},
            "scenarios.site.points[2]",
            "each x once",
        ),
        (
            {**RAMP, "points": [[0.0, 0.2], [2.5, 0.3]]},
            "scenarios.site.points[1]",
            "outside the bed",
        ),
        (
            {**RAMP, "points": [[0.0, 0.2], [1.0, 0.03]]},
            "scenarios.site.points[1]",
            "below a grain",
        ),
        (
            {**RAMP, "points": [[0.0, 0.2], [1.0, 60.0]]},
            "scenarios.site.points[1]",
            "above the bed's box",
        ),
        (
            {**RAMP, "points": [[0.0, float("nan")], [1.0, 0.3]]},
            "scenarios.site.points[0][1]",
            "finite",
        ),
        ({"kind": "profile"}, "scenarios.site.points", "needs it"),
        ({"kind": "dune"}, "scenarios.site.kind", "one of"),
        ({"points": [[0.0, 0.2], [1.0, 0.3]]}, "scenarios.site", "kind"),
        ({"kind": "heightmap", "file": "no/such/map.npy"}, "scenarios.site.file", "does not exist"),
        ({"kind": "heightmap", "file": "map.txt"}, "scenarios.site.file", "not a .npy or .csv"),
        ({**RAMP, "file": "map.npy"}, "scenarios.site.file", "takes points, not file"),
    ],
)
def test_terrain_that_cannot_be_built_is_refused_by_field(scenario, field, message):
    with pytest.raises(ConfigError) as exc:
        load_config(config_with(scenario))
    assert f"config field '{field}'" in str(exc.value)
    assert message in str(exc.value)


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.array([0.1, 0.2, 0.3]), "1-D array"),
        (np.ones((2, 2, 2)) * 0.2, "3-D array"),
        (np.array([["a", "b"], ["c", "d"]]), "not a 2-D array of numbers"),
        (np.array([[0.2, np.nan], [0.2, 0.2]]), "not finite, first at row 0, column 1"),
        (np.array([[0.2, np.inf], [0.2, 0.2]]), "not finite"),
        (np.array([[0.2, 0.01], [0.2, 0.2]]), "below a grain"),
        (np.array([[0.2, 51.0], [0.2, 0.2]]), "above the bed's box"),
    ],
)
def test_a_heightmap_that_is_not_heights_is_refused_naming_the_file(tmp_path, array, message):
    path = write_npy(tmp_path, array)
    with pytest.raises(ConfigError) as exc:
        load_config(config_with({"kind": "heightmap", "file": path}))
    assert "config field 'scenarios.site.file'" in str(exc.value) and message in str(exc.value)


def test_a_csv_heightmap_of_text_is_refused(tmp_path):
    path = tmp_path / "map.csv"
    path.write_text("0.2,0.3\n0.2,high\n")
    with pytest.raises(ConfigError, match=r"'scenarios.site.file'.*not a 2-D array of numbers"):
        load_config(config_with({"kind": "heightmap", "file": str(path)}))


def test_a_pickled_npy_is_refused_not_executed(tmp_path):
    path = tmp_path / "map.npy"
    np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ConfigError, match=r"'scenarios.site.file'.*not a 2-D array of numbers"):
        load_config(config_with({"kind": "heightmap", "file": str(path)}))


def test_sweep_points_name_defined_scenarios_and_transfer_only_unseen_ones():
    with pytest.raises(
        ConfigError, match=r"'sweep.transfer\[0\].scenario': scenario 'dune' is not defined"
    ):
        load_config({"sweep": {"transfer": [{"scenario": "dune", "speed": 1.0, "depth": 0.05}]}})
    with pytest.raises(
        ConfigError, match=r"'sweep.transfer\[0\].scenario': hill is in sweep.scenarios"
    ):
        load_config({"sweep": {"transfer": [{"scenario": "hill", "speed": 1.0, "depth": 0.05}]}})
    with pytest.raises(
        ConfigError, match=r"'sweep.transfer\[0\].depth': a 0.3 m cut is deeper than the site bed"
    ):
        load_config(config_with(RAMP, transfer=[{"scenario": "site", "speed": 1.0, "depth": 0.3}]))
    cfg = load_config(
        config_with(RAMP, transfer=[{"scenario": "site", "speed": 1.0, "depth": 0.1}])
    )
    assert cfg["sweep"]["transfer"][0]["scenario"] == "site"


def test_the_default_config_holds_the_trench_out():
    cfg = load_config("config/config.yaml")
    from dozerlab.sweep import by_role, sweep_points

    transfer = by_role(sweep_points(cfg), "transfer")
    assert transfer and {p.scenario for p in transfer} == {"trench"}
    assert "trench" not in cfg["sweep"]["scenarios"]
