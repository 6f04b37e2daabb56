"""The report's HTML pieces: numbers, tables, embedded images, the page."""

import base64
import struct

import pytest

from dozerlab.report import html


@pytest.mark.parametrize(
    ("value", "text"), [(0.0912, "9.1 %"), (1.0, "100.0 %"), (None, "–"), (float("nan"), "–")]
)
def test_percent(value, text):
    assert html.percent(value) == text


def test_table_puts_units_in_headings():
    cols = [html.Column("name", text=True), html.Column("force", "kN", lambda v: f"{v:.1f}")]
    out = html.table(cols, [["a", 1.25], [html.Group("group")]])
    assert '<th class="text">name</th><th>force (kN)</th>' in out
    assert "<td>1.2</td>" in out and '<td class="text" colspan="2">group</td>' in out


def test_images_of_each_kind_are_embedded(tmp_path):
    gif = tmp_path / "a.gif"
    gif.write_bytes(b"GIF89a")
    assert html.data_uri(gif).startswith("data:image/gif;base64,")
    with pytest.raises(ValueError, match="cannot embed"):
        html.data_uri(tmp_path / "a.txt")


@pytest.mark.parametrize(
    ("value", "text"),
    [(1.234567, "1.235"), (1234567.0, "1.235e+06"), (3, "3"), (None, "–"), (float("inf"), "–")],
)
def test_cells_read_to_four_significant_digits(value, text):
    assert html.fmt(value) == text


@pytest.mark.parametrize(
    ("value", "bound", "decimals", "text"),
    [
        (0.89998, 0.9, 2, "0.89998"),  # "0.90" would read as met beside "missed"
        (0.9004, 0.9, 2, "0.9004"),
        (0.9, 0.9, 2, "0.90"),
        (0.8123, 0.9, 2, "0.81"),
        (39.96, 40.0, 1, "39.96"),
        (0.9 - 1e-9, 0.9, 2, "0.900000"),  # no further than 6 decimals
        (None, 0.9, 2, "–"),
        (float("nan"), 0.9, 2, "–"),
    ],
)
def test_a_figure_judged_against_a_bound_never_rounds_onto_it(value, bound, decimals, text):
    assert html.against(value, bound, decimals) == text


def test_bytes_and_figures_are_embedded_as_base64():
    from matplotlib.figure import Figure

    uri = html.data_uri(b"<svg/>", "image/svg+xml")
    assert uri == "data:image/svg+xml;base64," + base64.b64encode(b"<svg/>").decode()
    fig = Figure(figsize=(2, 1))
    fig.subplots()
    png = base64.b64decode(html.data_uri(fig).removeprefix("data:image/png;base64,"))
    assert png.startswith(b"\x89PNG") and struct.unpack(">II", png[16:24]) == (
        2 * html.FIGURE_DPI,
        1 * html.FIGURE_DPI,
    )
    assert png[25] == 3  # the IHDR colour type: a palette PNG (html.palette_png)


def test_an_animation_is_a_file_beside_the_page_shown_by_relative_path(tmp_path):
    gif = tmp_path / "results" / "a.gif"
    gif.parent.mkdir()
    gif.write_bytes(b"GIF89a frames")
    out = html.animation(gif, tmp_path / "report", "reduced_a.gif", "NDEM & reduced")
    assert out == (
        '<figure><a href="animations/reduced_a.gif"><img src="animations/reduced_a.gif" '
        'alt="NDEM &amp; reduced" loading="lazy"></a><figcaption>NDEM &amp; reduced'
        "</figcaption></figure>"
    )
    assert (tmp_path / "report" / "animations" / "reduced_a.gif").read_bytes() == b"GIF89a frames"
    with pytest.raises(ValueError, match=r"a \.gif file name"):
        html.animation(gif, tmp_path / "report", "../a.gif", "up")


def test_the_summary_links_each_answer_to_its_section():
    out = html.summary([("Best force model", "mlp, 9 % < 10 %", "models")])
    assert out == (
        '<ul class="summary"><li><a href="#models"><b>Best force model</b></a>: '
        "mlp, 9 % &lt; 10 %</li></ul>"
    )
    assert html.verdict("a & b") == '<p class="verdict">a &amp; b</p>'


def test_page_escapes_text_links_its_sections_and_is_recognised_as_a_report(tmp_path):
    out = html.page("a <b> & c", [("one", "First & only", "<p>body</p>")], html.note("x < y"))
    assert "<title>a &lt;b&gt; &amp; c</title>" in out
    assert '<a href="#one">First &amp; only</a>' in out
    assert '<section id="one"><h2>First &amp; only</h2>\n<p>body</p>\n</section>' in out
    assert '<div class="note">x &lt; y</div>' in out
    (tmp_path / "index.html").write_text(out)
    (tmp_path / "other.html").write_text("<!DOCTYPE html><html><title>mine</title></html>")
    assert html.REPORT_PAGE.recognise(tmp_path / "index.html")
    assert not html.REPORT_PAGE.recognise(tmp_path / "other.html")
