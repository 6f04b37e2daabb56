import dataclasses
import json

import numpy as np
import pytest

from dozerlab.config import schema
from dozerlab.runtime import DozerlabError
from dozerlab.scenarios.bed import SCENARIOS, Bed


def test_save_load_round_trip_without_pickle(hill_bed, tmp_path):
    bed = dataclasses.replace(
        hill_bed,
        settle_time=np.array([0.05, 0.1]),
        settle_kinetic_energy=np.array([1.0, 0.5]),
        settle_contacts=np.array([10, 12]),
    )
    path = tmp_path / "hill.npz"
    bed.save(path)
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
        assert data["positions"].shape == (bed.count, 3)
    assert meta["scenario"] == "hill" and meta["material"]["density"] == 2600.0
    back = Bed.load(path)
    for name in (
        "positions",
        "radii",
        "masses",
        "velocities",
        "angular_velocities",
        "settle_time",
        "settle_kinetic_energy",
        "settle_contacts",
    ):
        np.testing.assert_array_equal(getattr(back, name), getattr(bed, name))
    assert (back.scenario, back.length, back.width, back.seed) == ("hill", 4.0, 1.2, 0)
    assert not list(tmp_path.glob(".*tmp*"))


def test_bad_scenario_and_shapes_are_refused(hill_bed):
    with pytest.raises(DozerlabError, match=r"Bed\.scenario 'a/b' holds a path separator"):
        Bed(
            "a/b",
            1.0,
            1.0,
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros(0),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            {},
            0,
        )
    with pytest.raises(ValueError, match="velocities"):
        Bed(
            "hill",
            1.0,
            1.0,
            np.zeros((2, 3)),
            np.ones(2),
            np.ones(2),
            np.zeros((3, 3)),
            np.zeros((2, 3)),
            {},
            0,
        )


def test_foreign_file_is_a_clear_error(tmp_path):
    np.savez(tmp_path / "x.npz", a=np.zeros(3))
    with pytest.raises(DozerlabError, match="not a dozerlab bed"):
        Bed.load(tmp_path / "x.npz")
    with pytest.raises(DozerlabError, match="not found"):
        Bed.load(tmp_path / "missing.npz")


def test_kinetic_energy_counts_translation_and_rotation():
    bed = Bed(
        "step",
        1.0,
        1.0,
        np.zeros((1, 3)),
        np.array([0.1]),
        np.array([2.0]),
        np.array([[1.0, 0.0, 0.0]]),
        np.array([[0.0, 10.0, 0.0]]),
        {},
        0,
    )
    assert bed.kinetic_energy_per_particle() == pytest.approx(
        0.5 * 2.0 + 0.5 * 0.4 * 2.0 * 0.01 * 100.0
    )


def test_scenario_names_are_the_schemas():
    assert tuple(schema()["properties"]["scenarios"]["properties"]) == SCENARIOS


def test_a_twin_bed_moves_every_grain_by_the_jitter_reproducibly(hill_bed):
    twin = hill_bed.jittered(1e-6, seed=7)
    moved = np.linalg.norm(twin.positions - hill_bed.positions, axis=1)
    np.testing.assert_allclose(moved, 1e-6, rtol=1e-6)
    np.testing.assert_array_equal(twin.positions, hill_bed.jittered(1e-6, seed=7).positions)
    assert not np.array_equal(twin.positions, hill_bed.jittered(1e-6, seed=8).positions)
    assert twin.info["jitter_m"] == 1e-6 and twin.count == hill_bed.count
