"""The section registry: every module of ``dozerlab.report.sections`` is a complete section."""

from dozerlab.report import sections


def test_every_section_module_is_complete():
    found = sections.modules()
    assert [m.ORDER for m in found] == sorted(m.ORDER for m in found)
    for m in found:
        assert isinstance(m.TITLE, str) and callable(m.render)
