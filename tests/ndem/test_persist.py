"""A World's parts saved as one .npz and loaded back as they were."""

import zipfile

import numpy as np
import pytest

from dozerlab.ndem.bodies import Bodies
from dozerlab.ndem.params import Parameters
from dozerlab.ndem.persist import load_world, save_world
from dozerlab.ndem.state import SPHERE_FIELDS, ZONE_FIELDS, WorldState
from dozerlab.runtime import DozerlabError


def _parts() -> tuple[Parameters, WorldState, Bodies]:
    params = Parameters(dt=0.004, iterations=12, slabs=3, gravity=(0.0, 0.0, -1.62))
    rng = np.random.default_rng(0)
    state = WorldState(time=0.4, step_count=100)
    state.append(
        x=rng.normal(size=(4, 3)),
        v=rng.normal(size=(4, 3)),
        w=rng.normal(size=(4, 3)),
        r=np.full(4, 0.05),
        m=np.ones(4),
        mu=np.full(4, 0.4),
        mur=np.full(4, 0.1),
        id=np.array([3, 1, 0, 2], dtype=np.int64),
    )
    state.warm.store(state.id, np.array([0]), np.array([-1]), np.arange(7.0)[None])
    bodies = Bodies()
    bodies.add_plane((0, 0, 0), (0, 0, 1), 0.5)
    bodies.add_box((1, 0, 0.2), (0.02, 0.3, 0.2), True, 0.6, None)
    bodies.force[1] = [10.0, 0.0, -2.0]
    return params, state, bodies


def test_round_trip_keeps_parameters_state_warm_start_and_bodies(tmp_path):
    params, state, bodies = _parts()
    params = params.with_(active_zone=True, zone_margin=0.4)
    state.awake[[0, 2]] = False
    state.rest[1] = 0.03
    save_world(tmp_path / "w.npz", params, state, bodies)
    p, s, b = load_world(tmp_path / "w.npz")
    assert (p.dt, p.iterations, p.slabs) == (0.004, 12, 3)
    assert (p.active_zone, p.zone_margin) == (True, 0.4)
    np.testing.assert_array_equal(p.gravity, [0.0, 0.0, -1.62])
    assert (s.time, s.step_count) == (0.4, 100)
    for name in SPHERE_FIELDS + ZONE_FIELDS:
        np.testing.assert_array_equal(getattr(s, name), getattr(state, name))
    np.testing.assert_array_equal(s.warm.lam, state.warm.lam)
    np.testing.assert_array_equal(s.warm.start, state.warm.start)
    np.testing.assert_array_equal(b.kinematic, [False, True])
    np.testing.assert_array_equal(b.force, bodies.force)
    np.testing.assert_array_equal(b.load_center, b.center)


def test_a_file_without_a_later_parameter_loads_its_default(tmp_path):
    save_world(tmp_path / "w.npz", *_parts())
    with np.load(tmp_path / "w.npz") as f:
        arrays = {
            k: f[k] for k in f.files if k not in ("param_slabs", "sphere_awake", "sphere_rest")
        }
    np.savez(tmp_path / "old.npz", **arrays)
    params, state, _ = load_world(tmp_path / "old.npz")
    assert params.slabs == Parameters().slabs
    assert state.awake.all() and not state.rest.any()  # before the active zone: all awake


def test_a_file_of_another_format_is_refused(tmp_path):
    np.savez(tmp_path / "other.npz", positions=np.zeros((2, 3)))
    with pytest.raises(DozerlabError, match=r"is not a dozerlab\.ndem World file"):
        load_world(tmp_path / "other.npz")


@pytest.mark.parametrize("damage", ["truncated", "flipped"])
def test_a_damaged_world_file_is_refused_naming_it(tmp_path, damage):
    """Every array's CRC-32 is checked: a zip error or changed bytes, never a traceback."""
    params, state, bodies = _parts()
    path = tmp_path / "w.npz"
    save_world(path, params, state, bodies)
    data = bytearray(path.read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    else:  # the last byte of the sphere positions
        with zipfile.ZipFile(path) as z:
            info = z.getinfo("sphere_x.npy")
        start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
        data[start + info.file_size - 1] ^= 0x04
    path.write_bytes(bytes(data))
    with pytest.raises(DozerlabError, match=rf"{path} is damaged"):
        load_world(path)


def test_a_state_with_nan_is_neither_saved_nor_loaded(tmp_path):
    params, state, bodies = _parts()
    state.x[2, 1] = np.nan
    with pytest.raises(
        DozerlabError, match=r"'sphere_x' holds 1 NaN/inf value\(s\), first in row 2"
    ):
        save_world(tmp_path / "w.npz", params, state, bodies)
    assert not (tmp_path / "w.npz").exists()
