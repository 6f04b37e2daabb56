"""The platform's report: one self-contained HTML page of a sweep's results.

The page is an introduction (what was swept, and for a smoke-test config a note saying so)
followed by the sections of :mod:`dozerlab.report.sections` that have data, each rendered from
the results directory. Every image is embedded, so the page opens from disk anywhere, also as
an MLflow artifact.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from dozerlab import __version__
from dozerlab.report import html
from dozerlab.report.sections import Context, modules
from dozerlab.runtime import atomic_output, job_outputs
from dozerlab.sweep import by_role, fmt_number, sweep_points

TITLE = "dozerlab report"


def build_report(
    cfg: Mapping[str, Any], results: str | Path, out: str | Path, processes: int = 1
) -> Path:
    """Write the report of the validated config's sweep, read from ``results``, to ``out``;
    ``processes`` draw the per-point figures side by side."""
    out = Path(out)
    with job_outputs(("--out", out, html.REPORT_PAGE)):
        ctx = Context(cfg, Path(results), tuple(sweep_points(cfg)), processes)
        text = render_report(ctx)
        with atomic_output(out, html.REPORT_PAGE) as tmp:
            tmp.write_text(text, encoding="utf-8")
    return out


def render_report(ctx: Context) -> str:
    """The report's HTML: the introduction and every section with data, in page order."""
    sections = []
    for module in modules():
        body = module.render(ctx)
        if body:
            sections.append((module.__name__.rsplit(".", 1)[-1], module.TITLE, body))
    intro = _intro(ctx)
    if not sections:
        intro += html.missing(f"No results under {ctx.results} yet.")
    return html.page(TITLE, sections, intro)


def _intro(ctx: Context) -> str:
    sweep, learn = ctx.cfg["sweep"], ctx.cfg["learn"]
    n = {r: len(by_role(ctx.points, r)) for r in ("train", "interpolation", "extrapolation")}
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    numbers = lambda xs: ", ".join(fmt_number(x) for x in xs)  # noqa: E731
    text = html.paragraph(
        f"dozerlab {__version__}, built {when}. Scenarios {', '.join(sweep['scenarios'])}; "
        f"blade speeds {numbers(sweep['speeds'])} m/s × cut depths {numbers(sweep['depths'])} m: "
        f"{n['train']} training points; held out of training, {n['interpolation']} interpolation "
        f"and {n['extrapolation']} extrapolation points. Models: {', '.join(learn['models'])}."
    )
    if ctx.cfg.get("report", {}).get("smoke_test"):
        text += html.note(
            f"Smoke test (report.smoke_test). This configuration checks that the pipeline runs "
            f"end to end, with {n['train']} training points and {learn['epochs']} training "
            "epochs: its forces and model errors are not results. The default sweep "
            "(config/config.yaml) is the experiment."
        )
    return text
