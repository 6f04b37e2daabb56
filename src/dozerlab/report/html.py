"""The report's shared building blocks: embedded images, animations beside the page, tables
with units, verdicts, the summary, notes, the page.

Every section builds its HTML from these, so the whole report looks alike. Still images (PNG,
SVG, JPEG files or matplotlib figures) are embedded as base64 data URIs; animations, which
would make the page tens of megabytes, are copied into the :data:`ANIMATIONS` folder beside it
and shown by relative path, so the page and that folder open from disk with no network and
travel together (the workflow attaches both to its MLflow run).
"""

from __future__ import annotations

import base64
import html
import io
import math
import shutil
import sys
from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dozerlab.runtime import ANIMATION, MARK, OutputKind, atomic_output, text_starts_with

_MIME = {
    ".png": "image/png",
    ".gif": "image/gif",
    ".svg": "image/svg+xml",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
}

#: The folder beside the page that holds its animations (``results/report/animations``).
ANIMATIONS = "animations"

#: Resolution of the report's own figures: 1 inch of figure is 100 px of page, so a 12 in wide
#: figure fills the page's width and a 12 pt label is 17 px high.
FIGURE_DPI = 100

# Images are shown at their own pixel size (never enlarged) so the figures' text keeps the size
# it was drawn with; the report's figures are drawn at 100 dpi for this page's 1200 px width.
_STYLE = """
body { font-family: system-ui, sans-serif; font-size: 16px; line-height: 1.45; margin: 1.5em auto;
       max-width: 1240px; padding: 0 1em; color: #222; }
h1 { font-size: 1.8em; margin-bottom: 0.2em; } h2 { font-size: 1.4em; margin-top: 1.8em;
border-bottom: 1px solid #ddd; padding-bottom: 0.2em; } h3 { font-size: 1.15em; }
nav { font-size: 0.95em; margin: 0.5em 0 1em; } nav a { margin-right: 1.2em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.65em; text-align: right; }
th { background: #f2f2f2; font-weight: 600; } tr.group td { background: #fafafa; font-weight: 600; }
td.text, th.text { text-align: left; } td.text { white-space: nowrap; }
figure { display: inline-block; margin: 0.6em 0.6em 0.6em 0; vertical-align: top; max-width: 100%; }
figure img { max-width: 100%; height: auto; border: 1px solid #e2e2e2; }
figcaption { font-size: 0.9em; color: #444; max-width: 60em; }
.summary { border: 1px solid #cfd8e3; background: #f5f8fb; padding: 0.7em 1em 0.7em 2.2em;
           margin: 0.8em 0 1em; } .summary li { margin: 0.25em 0; }
.verdict { font-weight: 600; }
.note { border-left: 4px solid #d08c00; background: #fff6e0; padding: 0.6em 1em; margin: 1em 0; }
.missing { color: #a33; }
.caption { color: #444; font-size: 0.95em; max-width: 60em; }
caption.caption { text-align: left; caption-side: top; padding-bottom: 0.3em; }
details { margin: 0.4em 0 0.8em; } summary { cursor: pointer; font-weight: 600; }
"""


def esc(value: Any) -> str:
    """HTML-escape ``str(value)``."""
    return html.escape(str(value))


def data_uri(source: bytes | str | Path | Any, mime: str = "image/png") -> str:
    """A base64 ``data:`` URI of an image file (PNG, GIF, SVG, JPEG: type from the suffix), of
    raw bytes of type ``mime``, or of a matplotlib figure (rendered as PNG at
    :data:`FIGURE_DPI`). PNGs are embedded with a palette of 256 colours (:func:`palette_png`)."""
    if isinstance(source, bytes):
        data = source
    elif isinstance(source, (str, Path)):
        path = Path(source)
        if path.suffix.lower() not in _MIME:
            raise ValueError(f"cannot embed {path}: not one of {sorted(_MIME)}")
        data, mime = path.read_bytes(), _MIME[path.suffix.lower()]
    else:
        buf = io.BytesIO()
        source.savefig(buf, format="png", dpi=FIGURE_DPI)
        if (plt := sys.modules.get("matplotlib.pyplot")) is not None:
            plt.close(source)  # a pyplot figure stays in pyplot's registry until closed
        data = buf.getvalue()
    if mime == "image/png":
        data = palette_png(data)
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def palette_png(data: bytes) -> bytes:
    """A PNG re-encoded with a palette of 256 colours: a plot's few colours and a colour map's
    steps survive, and the page's figures weigh a third to a quarter of their full-colour size
    (the quick sweep's 59: 5.0 MB → 1.4 MB)."""
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        # FASTOCTREE: as good as median cut on plots and several times faster
        palette = im.convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE)
    buf = io.BytesIO()
    palette.save(buf, format="PNG")
    return buf.getvalue()


def figure_style() -> AbstractContextManager[Any]:
    """A context in which matplotlib figures get the report's legible font sizes: create and
    draw a section's figure inside it."""
    import matplotlib

    return matplotlib.rc_context(
        {
            "font.size": 12,
            "axes.titlesize": 13,
            "axes.labelsize": 12,
            "xtick.labelsize": 11,
            "ytick.labelsize": 11,
            "legend.fontsize": 11,
            "figure.titlesize": 14,
        }
    )


def figure(source: bytes | str | Path | Any, caption: str) -> str:
    """An embedded image with a caption (see :func:`data_uri` for ``source``), shown at its own
    width, at most the page's."""
    return (
        f'<figure><img src="{data_uri(source)}" alt="{esc(caption)}">'
        f"<figcaption>{esc(caption)}</figcaption></figure>"
    )


def animation(source: str | Path, page_dir: Path, name: str, caption: str) -> str:
    """An animation (a GIF file ``source``) with a caption, shown from a copy beside the page:
    ``page_dir/animations/name``, linked by the relative path ``animations/name``. The copy is
    written through :func:`dozerlab.runtime.atomic_output`, so only an earlier animation of ours
    is replaced."""
    if Path(name).name != name or not name.endswith(".gif"):
        raise ValueError(f"an animation's name is a .gif file name, got {name!r}")
    dest = page_dir / ANIMATIONS / name
    dest.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(dest, ANIMATION) as tmp:
        shutil.copyfile(source, tmp)
    href = f"{ANIMATIONS}/{name}"
    return (
        f'<figure><a href="{esc(href)}"><img src="{esc(href)}" alt="{esc(caption)}" '
        f'loading="lazy"></a><figcaption>{esc(caption)}</figcaption></figure>'
    )


def percent(fraction: float | None, digits: int = 1) -> str:
    """A fraction as a percentage, ``0.0912`` → ``9.1 %``; None or NaN as an en dash."""
    if fraction is None or not math.isfinite(fraction):
        return "–"
    return f"{100 * fraction:.{digits}f} %"


def against(value: float | None, bound: float, decimals: int = 2) -> str:
    """``value`` to ``decimals`` decimals or, where rounding would carry it onto or across
    ``bound`` (a target it is judged against), to as many more as keep it on its own side, up to
    6: a skill of 0.89998 against a target of 0.9 reads ``0.89998``, not ``0.90`` beside "missed".
    None or NaN as an en dash."""
    if value is None or not math.isfinite(value):
        return "–"
    side = (value > bound) - (value < bound)
    for d in range(decimals, 7):
        text = f"{value:.{d}f}"
        rounded = float(text)
        if (rounded > bound) - (rounded < bound) == side:
            break
    return text


def fmt(value: Any) -> str:
    """A table cell's default text: floats to 4 significant digits, None or NaN as an en dash."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


@dataclass(frozen=True)
class Column:
    """A table column: its heading, its unit (shown in the heading; ``""`` for none, ``"%"`` for
    percentages), how a value reads (default :func:`fmt`) and whether it is text (left-aligned)."""

    name: str
    unit: str = ""
    format: Callable[[Any], str] = fmt
    text: bool = False

    @property
    def heading(self) -> str:
        return f"{self.name} ({self.unit})" if self.unit else self.name


class Group(str):
    """A table row heading (see :func:`table`)."""


def table(columns: Sequence[Column], rows: Iterable[Sequence[Any]], caption: str = "") -> str:
    """A table with the unit of each column in its heading. A row whose first cell is a
    :class:`Group` is a heading row spanning the table."""

    def cell(tag: str, col: Column, text: str) -> str:
        cls = ' class="text"' if col.text else ""
        return f"<{tag}{cls}>{esc(text)}</{tag}>"

    head = "".join(cell("th", c, c.heading) for c in columns)
    body = []
    for r in rows:
        if r and isinstance(r[0], Group):
            body.append(
                f'<tr class="group"><td class="text" colspan="{len(columns)}">{esc(r[0])}</td></tr>'
            )
        else:
            body.append(
                "<tr>"
                + "".join(cell("td", c, c.format(v)) for c, v in zip(columns, r, strict=True))
                + "</tr>"
            )
    cap = f'<caption class="caption">{esc(caption)}</caption>' if caption else ""
    return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def paragraph(text: str, cls: str = "") -> str:
    """A paragraph of plain text (escaped); ``cls`` a CSS class such as ``caption``."""
    attr = f' class="{cls}"' if cls else ""
    return f"<p{attr}>{esc(text)}</p>"


def verdict(text: str) -> str:
    """A section's verdict: the one sentence (plain text, escaped) that answers its question."""
    return paragraph(text, "verdict")


def summary(lines: Sequence[tuple[str, str, str]]) -> str:
    """The page's summary: a list of ``(question, answer, section id)``, each answer (plain
    text) after its question and a link to the section that shows the evidence."""
    items = "".join(
        f'<li><a href="#{esc(anchor)}"><b>{esc(question)}</b></a>: {esc(answer)}</li>'
        for question, answer, anchor in lines
    )
    return f'<ul class="summary">{items}</ul>'


def note(text: str) -> str:
    """A highlighted note (plain text, escaped), e.g. that a sweep is a smoke test."""
    return f'<div class="note">{esc(text)}</div>'


def missing(text: str) -> str:
    """A line saying what is not there yet."""
    return f'<p class="missing">{esc(text)}</p>'


def details(summary: str, body: str, anchor: str = "") -> str:
    """A collapsed block: ``summary`` (plain text) over ``body`` (HTML); ``anchor`` an id to
    link to."""
    attr = f' id="{esc(anchor)}"' if anchor else ""
    return f"<details{attr}><summary>{esc(summary)}</summary>{body}</details>"


def page(title: str, sections: Sequence[tuple[str, str, str]], intro: str = "") -> str:
    """A complete HTML document: the title, ``intro`` (HTML), a table of contents and the
    sections, each ``(id, heading, body HTML)``."""
    nav = "".join(f'<a href="#{esc(i)}">{esc(h)}</a>' for i, h, _ in sections)
    body = "\n".join(
        f'<section id="{esc(i)}"><h2>{esc(h)}</h2>\n{b}\n</section>' for i, h, b in sections
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<meta name="generator" content="{MARK}">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{esc(title)}</title><style>{_STYLE}</style></head>\n<body>\n"
        f"<h1>{esc(title)}</h1>\n{intro}\n<nav>{nav}</nav>\n{body}\n</body></html>\n"
    )


#: What :func:`page` writes (``dozerlab report``); recognised by its generator tag.
REPORT_PAGE = OutputKind(
    "a dozerlab report page", text_starts_with(f'<meta name="generator" content="{MARK}">')
)
