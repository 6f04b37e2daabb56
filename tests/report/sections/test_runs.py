"""The runs section: a collapsed block of figures per built point, the others listed."""

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.sections import runs
from tests.helpers import SMALL_SWEEP, png_file, report_context

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
