import numpy as np
import pytest
import torch

from dozerlab.learn.data import (
    check_grid,
    concat,
    load_store,
    split_train_validation,
    with_loop_fields,
)
from dozerlab.learn.models import ForceModel
from dozerlab.learn.train import Batches, fit_normalization
from dozerlab.learn.validate import check_no_leak
from dozerlab.runtime import DozerlabError
from tests.helpers import in_memory


def test_split_is_a_trailing_block_per_store_and_history_stays_in_store():
    stores = [in_memory(0.5, 0.05, steps=40, seed=1), in_memory(1.5, 0.15, steps=60, seed=2)]
    samples = concat(stores, history=4)
    assert len(samples) == (40 - 3) + (60 - 3)
    train, val = split_train_validation(samples, 0.25)
    for k, steps in enumerate((40, 60)):
        t = train.index[train.store_of == k]
        v = val.index[val.store_of == k]
        assert t.max() < v.min() and v.size == round(0.25 * (steps - 3))
    rows = samples.rows(np.arange(len(samples)))
    starts = np.array([0, 40])
    assert all(
        ((r >= starts[s]) & (r < starts[s] + (40, 60)[s])).all()
        for r, s in zip(rows, samples.store_of, strict=False)
    )


def test_spread_blocks_cover_the_run_and_no_training_input_touches_them():
    store = in_memory(0.5, 0.05, steps=203, seed=1)
    samples = concat([store], history=3)
    train, val = split_train_validation(samples, 0.15, block=10)
    assert 0.1 < len(val) / len(samples) < 0.2
    assert val.index.min() < 100 < val.index.max()  # not just the end of the run
    train_rows = set(train.rows(np.arange(len(train))).ravel())
    assert train_rows.isdisjoint(val.index)
    assert set(train.index).isdisjoint(val.index)
    # a store shorter than four blocks keeps the trailing block
    short_train, short_val = split_train_validation(
        concat([in_memory(0.5, 0.05, steps=30, seed=1)], 3), 0.25, block=10
    )
    assert short_train.index.max() < short_val.index.min() and short_val.index.max() == 29


@pytest.mark.parametrize("block", [0, 5])
def test_normalisation_uses_training_block_only(block):
    store = in_memory(1.0, 0.1, steps=50, seed=3)
    train, val = split_train_validation(concat([store], 1), 0.2, block)
    store.target[val.index] = 1e9  # only the validation block is poisoned
    store.density[val.index] = 1e9
    model = ForceModel("linear", store.grid)
    fit_normalization(model, Batches(train, torch.device("cpu")))
    assert float(model.y_mean.abs().max()) < 1e5
    assert float(model.chan_mean.abs().max()) < 1e5


def test_held_out_point_that_was_trained_on_is_refused():
    meta = {"train_keys": [("hill", 0.5, 0.05)], "train_sources": []}
    check_no_leak(meta, [in_memory(1.0, 0.1)])
    with pytest.raises(DozerlabError, match="trained on"):
        check_no_leak(meta, [in_memory(0.5, 0.05)])


def test_stores_round_trip_and_grid_mismatch_is_clear(store_files):
    s = load_store(store_files["train"][0])
    assert s.velocity.dtype == np.float32 and s.velocity.flags.c_contiguous
    assert s.grid == (8, 6, 4) and s.point["scenario"] == "hill"
    other = load_store(store_files["other_grid"][0])
    with pytest.raises(DozerlabError, match=r"\(6, 6, 4\) grid but the model expects \(8, 6, 4\)"):
        check_grid([s, other])
    with pytest.raises(DozerlabError, match="grid"):
        concat([s, other], 1)


# xarray's to_zarr consolidates, and zarr notes that consolidated metadata is outside the v3 spec
@pytest.mark.filterwarnings("ignore:Consolidated metadata:UserWarning")
def test_missing_array_is_named(store_files, tmp_path):
    import xarray as xr

    broken = tmp_path / "broken.zarr"
    xr.open_zarr(store_files["train"][0]).drop_vars("force").to_zarr(broken)
    with pytest.raises(ValueError, match="force"):
        load_store(broken)


def test_stores_of_other_bin_sizes_are_refused(store_files):
    a, b = (load_store(p) for p in store_files["train"][:2])
    assert a.bin_size == (0.1, 0.1, 0.1)
    assert check_grid([a, b], a.grid, [0.1, 0.1, 0.1]) == a.grid
    b.bin_size = (0.1, 0.12, 0.1)  # same counts over a wider volume
    with pytest.raises(DozerlabError, match=r"bins of \[0.1, 0.12, 0.1\] m but the model expects"):
        check_grid([a, b])
    with pytest.raises(DozerlabError, match="bins of"):
        check_grid([a], a.grid, [0.2, 0.1, 0.1])


def test_loop_fields_pair_the_loops_velocity_and_density_with_ndems_force():
    ndem, loop = in_memory(1.0, 0.1, seed=1), in_memory(1.0, 0.1, seed=2)
    paired = with_loop_fields(ndem, loop)
    np.testing.assert_array_equal(paired.velocity, loop.velocity)
    np.testing.assert_array_equal(paired.density, loop.density)
    np.testing.assert_array_equal(paired.target, ndem.target)
    np.testing.assert_array_equal(paired.blade_velocity, ndem.blade_velocity)
    assert paired.point == ndem.point and not np.array_equal(paired.velocity, ndem.velocity)
    with pytest.raises(DozerlabError, match="different points"):
        with_loop_fields(ndem, in_memory(1.0, 0.2, seed=2))
    with pytest.raises(DozerlabError, match=r"different rows \(80 and 100"):
        with_loop_fields(ndem, in_memory(1.0, 0.1, seed=2, steps=80))
    with pytest.raises(DozerlabError, match="grid"):
        with_loop_fields(ndem, in_memory(1.0, 0.1, seed=2, grid=(6, 6, 4)))


def test_stores_of_another_blade_part_are_refused(store_files):
    a, b = (load_store(p) for p in store_files["train"][:2])
    assert a.blade_part is None and a.part == (0, 0, 6, 4)
    b.blade_part = (0, 1, 5, 4)  # the same bins, split into a blade part and side bins
    with pytest.raises(DozerlabError, match=r"blade part at bins \[0, 1, 5, 4\].*side_bins"):
        check_grid([a, b])
    with pytest.raises(DozerlabError, match="blade part"):
        check_grid([a], a.grid, blade_part=(2, 0, 6, 4))
    with pytest.raises(DozerlabError, match="four bin indices"):
        check_grid([a], a.grid, blade_part=(0, 6, 4))
