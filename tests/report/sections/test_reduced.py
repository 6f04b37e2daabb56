"""The reduced-simulation section: per dynamics model its table with the targets, per point
its plots and animation."""

import json

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.sections import reduced
from tests.helpers import SMALL_SWEEP, png_file, report_context

CFG = load_config(SMALL_SWEEP)
TARGETS = {
    "height_accuracy": 0.8,
    "force_rmse": 0.25,
    "loop_speedup": 50,
    "job_speedup": 5,
    "max_overlap": 0.1,
}


def _comparison(results, model: str) -> None:
    point = {
        "scenario": "hill",
        "speed": 0.75,
        "depth": 0.1,
        "role": "interpolation",
        "height_accuracy": 0.9,
        "force_x_rel_rmse": 0.3,
        "velocity_rel_l2": 0.2,
        "density_rel_l2": 0.1,
        "final_emd_m": 0.0042,
        "max_overlap_loop": 0.05,
        "left_bed": 0,
        "loop_speedup": 62.0,
        "job_speedup": None,
        "targets_met": {"height_accuracy": True, "force_rmse": False, "job_speedup": None},
        "plots": ["hill_speed~0.75_depth~0.1_force.png", "hill_speed~0.75_depth~0.1.gif", "x.png"],
    }
    path = P.reduced_comparison_path(results, model)
    compare = path.with_suffix("") / "compare"
    png_file(compare / point["plots"][0], "force")
    (compare / point["plots"][1]).write_bytes(b"GIF89a")
    path.write_text(json.dumps({"targets": TARGETS, "points": [point]}))


def test_a_comparison_becomes_a_table_and_a_block_of_plots(tmp_path):
    assert reduced.render(report_context(CFG, tmp_path)) is None
    _comparison(tmp_path, "replay")
    text = reduced.render(report_context(CFG, tmp_path))
    assert "<h3>replay</h3>" in text and "replay feeds the loop NDEM's own fields" in (
        text.replace("&#x27;", "'")
    )
    assert (
        "targets: height accuracy ≥ 80%, force x rel. RMSE ≤ 25%, loop ≥ 50×, job ≥ 5×, "
        "overlap ≤ 10% of a radius, nothing left the bed" in text
    )
    cells = (
        "<td>90.0</td><td>30.0</td><td>20.0</td><td>10.0</td><td>4.2</td><td>5.0</td>"
        "<td>0</td><td>62.0</td><td>–</td>"
    )
    assert cells in text
    assert (
        "<summary>hill: speed 0.75 m/s, depth 0.1 m — targets missed: force_rmse</summary>" in text
    )
    assert "data:image/png;base64," in text and "data:image/gif;base64," in text
    assert text.count("<figure>") == 2  # the listed plot that is not there is left out
