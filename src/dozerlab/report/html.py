"""A small builder of self-contained HTML pages: tables and figures embedded as base64 PNGs.

The page opens from disk with no network and no neighbouring files, so it can be mailed,
attached to an MLflow run or served as is.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from dozerlab.runtime import MARK, OutputKind, text_starts_with

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
h1, h2, h3 { font-weight: 600; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f2f2; }
td.text, th.text { text-align: left; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
figure img { max-width: 560px; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; color: #555; }
.missing { color: #a33; }
details { margin: 0.5em 0 1em; }
"""


def esc(value: Any) -> str:
    """HTML-escape ``str(value)``."""
    return html.escape(str(value))


def png_data_uri(source: bytes | str | Path | Any) -> str:
    """A ``data:image/png;base64,…`` URI of PNG bytes, a PNG file or a matplotlib figure.

    A figure is rendered at 100 dpi and closed (the report builds many).
    """
    if isinstance(source, bytes):
        data = source
    elif isinstance(source, (str, Path)):
        data = Path(source).read_bytes()
    else:
        import matplotlib.pyplot as plt

        buf = io.BytesIO()
        source.savefig(buf, format="png", dpi=100, bbox_inches="tight")
        plt.close(source)
        data = buf.getvalue()
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def figure(source: bytes | str | Path | Any, caption: str) -> str:
    """An embedded PNG with a caption (see :func:`png_data_uri` for ``source``)."""
    return (
        f'<figure><img src="{png_data_uri(source)}" alt="{esc(caption)}">'
        f"<figcaption>{esc(caption)}</figcaption></figure>"
    )


def table(headers: Sequence[str], rows: Iterable[Sequence[Any]], text_columns: int = 1) -> str:
    """A table; the first ``text_columns`` columns are left-aligned, numbers right-aligned.

    Floats are shown with 4 significant digits; None as an en dash.
    """

    def cell(tag: str, i: int, value: Any) -> str:
        cls = ' class="text"' if i < text_columns else ""
        return f"<{tag}{cls}>{esc(fmt(value))}</{tag}>"

    head = "".join(cell("th", i, h) for i, h in enumerate(headers))
    body = "".join(
        "<tr>" + "".join(cell("td", i, v) for i, v in enumerate(r)) + "</tr>" for r in rows
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def fmt(value: Any) -> str:
    """A table cell's text: floats to 4 significant digits, None as an en dash."""
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def page(title: str, body: Sequence[str]) -> str:
    """A complete HTML document."""
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<meta name="generator" content="{MARK}">'
        f"<title>{esc(title)}</title><style>{_STYLE}</style></head>\n<body>\n"
        f"<h1>{esc(title)}</h1>\n" + "\n".join(body) + "\n</body></html>\n"
    )


#: What :func:`page` writes (``dozerlab report``); recognised by its generator tag.
REPORT_PAGE = OutputKind(
    "a dozerlab report page", text_starts_with(f'<meta name="generator" content="{MARK}">')
)
