"""The beds section: one figure per scenario whose bed file exists."""

from dozerlab.config import load_config
from dozerlab.report.sections import beds
from tests.helpers import SMALL_SWEEP, report_bed, report_context

CFG = load_config(SMALL_SWEEP)


def test_a_bed_file_becomes_one_captioned_figure(tmp_path):
    assert beds.render(report_context(CFG, tmp_path)) is None
    report_bed(tmp_path)
    text = beds.render(report_context(CFG, tmp_path))
    assert text.count("<figure>") == 1 and "data:image/png;base64," in text
    assert "The settled hill bed" in text and "40 particles in a 1 m × 0.5 m box" in text
