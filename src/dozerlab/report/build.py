"""The platform's report: one self-contained HTML page of a sweep's results.

Sections: the sweep table (each point's role, particle count, steps, wall time, mean and peak
blade force), the beds, per point its trajectory, a field slice and its force series, and the
model comparison on the held-out points with each model's validation section (written by
``dozerlab.learn.validate.html_section``). Every image is embedded as a base64 PNG, so the page
opens from disk anywhere, also as an MLflow artifact.
"""

from __future__ import annotations

import html as htmllib
import json
import os
import re
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from dozerlab import __version__
from dozerlab.report import html
from dozerlab.report.collect import HEADERS, point_figures, summarize
from dozerlab.runtime import atomic_output, check_output
from dozerlab.sweep import SweepPoint, bed_path, sweep_points, validation_path

#: Components of the model comparison table (the blade's draft force, lift and pitch torque).
COMPARED = ("force_x", "force_z", "torque_y")
_SRC = re.compile(r'src="([^"]+)"')


def build_report(cfg: Mapping[str, Any], results: str | Path, out: str | Path) -> Path:
    """Write the report of the validated config's sweep, read from ``results``, to ``out``."""
    results, out = Path(results), Path(out)
    check_output(out, html.REPORT_PAGE)
    points = sweep_points(cfg)
    body = [
        _intro(cfg, points),
        _sweep_table(results, points),
        _beds(results, points),
        _points(results, points),
        _models(cfg, results, out.parent),
    ]
    text = html.page("dozerlab report", body)
    with atomic_output(out, html.REPORT_PAGE) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return out


def _intro(cfg: Mapping[str, Any], points: list[SweepPoint]) -> str:
    sweep = cfg["sweep"]
    counts = {
        r: sum(p.role == r for p in points) for r in ("train", "interpolation", "extrapolation")
    }
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    return (
        f"<p>dozerlab {html.esc(__version__)}, {when}. Scenarios {html.esc(', '.join(sweep['scenarios']))}; "
        f"blade speeds {html.esc(sweep['speeds'])} m/s × cut depths {html.esc(sweep['depths'])} m: "
        f"{counts['train']} training points, {counts['interpolation']} interpolation and "
        f"{counts['extrapolation']} extrapolation points held out of training.</p>"
    )


def _sweep_table(results: Path, points: list[SweepPoint]) -> str:
    rows = [summarize(results, p).row() for p in points]
    return "<h2>Sweep</h2>" + html.table(HEADERS, rows, text_columns=2)


def _beds(results: Path, points: list[SweepPoint]) -> str:
    figs = []
    for scenario in dict.fromkeys(p.scenario for p in points):
        png = bed_path(results, scenario, "png")
        if png.is_file():
            figs.append(html.figure(png, f"settled {scenario} bed"))
    return "<h2>Beds</h2>" + ("".join(figs) or '<p class="missing">no bed plots yet</p>')


def _points(results: Path, points: list[SweepPoint]) -> str:
    parts = ["<h2>Sweep points</h2>"]
    for p in points:
        parts.append(
            f"<details><summary>{html.esc(p.scenario)} {html.esc(p.name)} ({html.esc(p.role)})</summary>"
            + "".join(point_figures(results, p))
            + "</details>"
        )
    return "\n".join(parts)


def _models(cfg: Mapping[str, Any], results: Path, html_dir: Path) -> str:
    found = [(m, validation_path(results, m)) for m in cfg["learn"]["models"]]
    found = [(m, p) for m, p in found if p.is_file()]
    if not found:
        return '<h2>Models</h2><p class="missing">no validation results yet</p>'
    from dozerlab.learn.validate import html_section

    rows = []
    for model, path in found:
        groups = json.loads(path.read_text())["groups"]
        for group, data in groups.items():
            m = data["overall"]
            rows.append(
                [model, group] + [v for c in COMPARED for v in (m[c]["rel_rmse"], m[c]["r2"])]
            )
    headers = ["model", "held-out group"] + [
        f"{c} {k}" for c in COMPARED for k in ("rel. RMSE", "R²")
    ]
    sections = [inline_images(html_section(path, html_dir), html_dir) for _, path in found]
    return (
        "<h2>Models on held-out points</h2>"
        "<p>Relative RMSE is the RMSE over the RMS of the measured value.</p>"
        + html.table(headers, rows, text_columns=2)
        + "".join(
            f"<details><summary>{html.esc(m)}</summary>{s}</details>"
            for (m, _), s in zip(found, sections, strict=False)
        )
    )


def inline_images(fragment: str, base: str | Path) -> str:
    """Replace ``src`` links to PNG files (relative to ``base``) by embedded data URIs.

    Links that are already data URIs or whose file is missing are left as they are.
    """

    def embed(m: re.Match[str]) -> str:
        # lexically: the report's directory may not exist yet, and ".." needs it on POSIX
        target = Path(os.path.normpath(Path(base) / htmllib.unescape(m[1])))
        if m[1].startswith("data:") or not target.is_file():
            return m[0]
        return f'src="{html.png_data_uri(target)}"'

    return _SRC.sub(embed, fragment)
