"""Figures of a reduced run next to NDEM's: the surface they draw, marked PNGs and GIF."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from dozerlab.fields.store import open_store
from dozerlab.reduce import plots
from dozerlab.reduce.compare import compare_point
from dozerlab.runtime import ANIMATION, FIGURE, OutputExistsError


def test_surface_is_the_top_of_the_bins_fuller_than_a_third_averaged_over_y():
    rho = np.zeros((1, 2, 2, 3))  # x, y, z bins; z centres 0.05, 0.15, 0.25 m
    rho[0, 0, 0, :2] = 1500.0  # two full bins: top 0.2 m
    rho[0, 0, 1, 0] = 1500.0  # one: top 0.1 m
    rho[0, 0, 1, 2] = 400.0  # under a third of solid: not material
    ds = xr.Dataset(
        {"density": (("time", "x", "y", "z"), rho)},
        coords={"z": [0.05, 0.15, 0.25], "x": [0.1, 0.3], "y": [-0.1, 0.1]},
    )
    # x = 0.1: mean of 0.2 and 0.1 m; x = 0.3, empty: the bottom face, 0 m
    np.testing.assert_allclose(plots.surface(ds, 0, 1500.0), [0.15, 0.0], atol=1e-12)


def test_the_comparison_plots_and_animation_are_dozerlab_outputs_and_replace_nothing_else(
    ndem_run, tmp_path
):
    tmp, config = ndem_run
    store, state = tmp / "ndem.zarr", tmp / "ndem.npz"
    twin = (store, state)  # NDEM as its own twin: the plots draw a third run
    metrics, series = compare_point(store, store, tmp / "bed.npz", state, state, config, twin=twin)
    metrics = {**metrics, "dynamics_model": "replay"}
    for draw in (plots.plot_force, plots.plot_errors, plots.plot_height, plots.plot_surface):
        out = draw(series, metrics, tmp_path / f"{draw.__name__}.png")
        assert FIGURE.recognise(out)
    ds = open_store(store)
    gif = plots.animate_pair(ds, ds, tmp_path / "pair.gif", frames=2)
    assert ANIMATION.recognise(gif)
    mine = tmp_path / "mine.png"
    mine.write_text("mine")
    with pytest.raises(OutputExistsError, match=r"mine\.png"):
        plots.plot_force(series, metrics, mine)
    assert mine.read_text() == "mine"
