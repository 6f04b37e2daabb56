"""The runs section: a collapsed block of figures per built point, the others listed."""

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.sections import runs
from tests.helpers import SMALL_SWEEP, png_file, report_context, report_store

CFG = load_config(SMALL_SWEEP)


def test_built_points_get_a_block_and_the_rest_are_named(tmp_path):
    assert runs.render(report_context(CFG, tmp_path)) is None
    first = P.sweep_points(CFG)[0]
    png_file(P.trajectory_path(tmp_path, first, "png"), "path")
    text = runs.render(report_context(CFG, tmp_path))
    assert text.count("<details>") == 1
    assert "<summary>hill: speed 0.5 m/s, depth 0.1 m (training)</summary>" in text
    assert (
        "Not built yet: hill speed~1.0_depth~0.1, hill speed~0.75_depth~0.1, "
        "hill speed~2.0_depth~0.1." in text
    )


def test_the_verdict_names_the_largest_force_and_flags_runs_that_peak_at_their_end(tmp_path):
    assert runs.verdict(report_context(CFG, tmp_path)) is None
    first = P.sweep_points(CFG)[0]
    report_store(
        P.field_path(tmp_path, first), first
    )  # |F| 2.02 kN in its last row, 1.04 kN before
    assert runs.verdict(report_context(CFG, tmp_path)) == (
        "1 run, each with its blade trajectory, a mid-run field slice and the blade force over "
        "time; the sweep's largest |F|, 2.02 kN, is that of hill 0.5 m/s, 0.1 m at t = 0.06 s of "
        "0.06 s; 1 of 1 runs peak in their last 10 %, where the pile ahead of the blade may "
        "press against the bed's far wall (trajectory.end_margin)."
    )
