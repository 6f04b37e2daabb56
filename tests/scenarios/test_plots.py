"""Figures of beds: particles drawn to scale, the surface seen from above, with colour bars."""

import numpy as np
from matplotlib.collections import EllipseCollection

from dozerlab.scenarios.plots import bed_figure, plot_bed


def test_bed_figure_draws_every_particle_to_scale(hill_bed, tmp_path):
    fig = bed_figure(hill_bed)
    side, plan, _log = fig.axes
    (discs,) = [c for c in side.collections if isinstance(c, EllipseCollection)]
    # one disc per particle, its diameter in data units (m), on equal-aspect axes
    assert discs.get_offsets().shape == (hill_bed.count, 2)
    np.testing.assert_allclose(np.sort(discs.get_widths()), np.sort(2 * hill_bed.radii))
    assert side.get_aspect() == 1.0 and plan.get_aspect() == 1.0
    colour_bars = [c.get_ylabel() for ax in (side, plan) for c in ax.child_axes]
    assert colour_bars == ["y (m)", "surface height (m)"]
    # the surface seen from above reaches the tallest column's top
    top = (hill_bed.positions[:, 2] + hill_bed.radii).max()
    assert np.isclose(plan.images[0].get_array().max(), top)
    plot_bed(hill_bed, tmp_path / "bed.png")
    assert (tmp_path / "bed.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
