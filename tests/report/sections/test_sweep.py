"""The sweep section: the map and the table of every sweep point."""

import re

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.collect import PointSummary
from dozerlab.report.sections import sweep
from tests.helpers import SMALL_SWEEP, report_context, report_store

CFG = load_config(SMALL_SWEEP)


def test_nothing_built_leaves_the_section_out(tmp_path):
    assert sweep.render(report_context(CFG, tmp_path)) is None


def test_one_row_per_point_and_the_map_with_its_colour_scale(tmp_path):
    points = P.sweep_points(CFG)
    report_store(P.field_path(tmp_path, points[2]), points[2])
    text = sweep.render(report_context(CFG, tmp_path))
    rows = re.findall(r"<tr>(.*?)</tr>", text)
    assert len(rows) == 1 + len(points)  # heading and one row per point, built or not
    assert text.count("data:image/png;base64,") == 1
    summaries = [PointSummary(p) for p in points]
    summaries[2].mean_force = 1500.0
    fig = sweep.sweep_map(summaries)
    assert isinstance(fig, Figure)
    panel, colorbar = fig.axes
    assert panel.get_title() == "hill" and colorbar.get_ylabel() == "mean |F| (kN)"
    assert [t.get_text() for t in panel.texts] == ["1.50 kN"]  # only the built point is labelled
    # the legend's markers are drawn as the points: filled from the colour scale, edged by
    # role, at their size; with a point not built, its hollow grey marker is explained too
    legend = fig.legends[0]
    labels = [t.get_text() for t in legend.get_texts()]
    assert labels == [*sweep.LABELS.values(), "not simulated yet"]
    drawn = panel.collections[2]  # the built point
    handle = legend.legend_handles[list(sweep.LABELS).index(points[2].role)]
    assert handle.get_markeredgecolor() == sweep.EDGES[points[2].role][0]
    assert handle.get_markerfacecolor() != "0.85"  # not the grey of a point not built
    assert round(handle.get_markersize() ** 2) == sweep.MARKER_AREA == drawn.get_sizes()[0]
    assert handle.get_markeredgewidth() == drawn.get_linewidths()[0]


def test_a_scenario_of_transfer_points_only_has_its_panel_marked_unseen():
    cfg = load_config(
        {
            **SMALL_SWEEP,
            "sweep": {
                **SMALL_SWEEP["sweep"],
                "transfer": [{"scenario": "trench", "speed": 1.0, "depth": 0.1}],
            },
        }
    )
    summaries = [PointSummary(p) for p in P.sweep_points(cfg)]
    summaries[0].mean_force = summaries[-1].mean_force = 1500.0
    fig = sweep.sweep_map(summaries)
    assert [ax.get_title() for ax in fig.axes[:2]] == ["hill", "trench (unseen terrain)"]
    assert fig.axes[1].collections[0].get_paths()  # the triangle of the transfer point
    row = sweep._row(summaries[-1])
    assert row[:2] == ["trench", "held out, unseen terrain"]


def test_the_legend_lies_inside_the_figure_however_many_scenarios():
    """On one scenario's narrow figure, three columns of role labels ran past both edges."""
    for cfg in (
        CFG,
        load_config(
            {
                **SMALL_SWEEP,
                "sweep": {
                    **SMALL_SWEEP["sweep"],
                    "transfer": [{"scenario": "trench", "speed": 1.0, "depth": 0.1}],
                },
            }
        ),
    ):
        summaries = [PointSummary(p) for p in P.sweep_points(cfg)]
        summaries[0].mean_force = 1500.0  # the rest not built: "not simulated yet" too
        fig = sweep.sweep_map(summaries)
        canvas = FigureCanvasAgg(fig)  # as the report's savefig draws it
        canvas.draw()
        renderer = canvas.get_renderer()
        box, frame = fig.legends[0].get_window_extent(renderer), fig.bbox
        assert frame.x0 <= box.x0 and box.x1 <= frame.x1, (box, frame)
        assert frame.y0 <= box.y0 and box.y1 <= frame.y1, (box, frame)
