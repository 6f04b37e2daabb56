"""The platform's report: one HTML page of a sweep's results and its animations beside it.

The page is an introduction (what was swept, and for a smoke-test config a note saying so), a
summary (each section's verdict that answers one of the page's questions) and the sections of
:mod:`dozerlab.report.sections` that have data, each opening with its verdict. Still images are
embedded; animations are files in the ``animations`` folder beside the page (a few megabytes
each would make the page tens of megabytes), so the page and that folder open from disk
anywhere, also as MLflow artifacts.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from dozerlab import __version__
from dozerlab.report import html
from dozerlab.report.sections import Context, modules
from dozerlab.runtime import ANIMATION, OutputExistsError, atomic_output, check_output, job_outputs
from dozerlab.sweep import ROLES, by_role, fmt_number, sweep_points

TITLE = "dozerlab report"


def build_report(
    cfg: Mapping[str, Any], results: str | Path, out: str | Path, processes: int = 1
) -> Path:
    """Write the report of the validated config's sweep, read from ``results``, to ``out`` and
    its animations to the ``animations`` folder beside it (earlier animations of ours that the
    page no longer shows are removed); ``processes`` draw the per-point figures side by side."""
    out = Path(out)
    with job_outputs(("--out", out, html.REPORT_PAGE)):
        ctx = Context(cfg, Path(results), tuple(sweep_points(cfg)), out.parent, processes)
        text = render_report(ctx)
        with atomic_output(out, html.REPORT_PAGE) as tmp:
            tmp.write_text(text, encoding="utf-8")
        # made also when empty: the workflow's output is the page's folder with this one in it
        (out.parent / html.ANIMATIONS).mkdir(exist_ok=True)
        _remove_unshown_animations(out.parent / html.ANIMATIONS, text)
    return Path(out)


def render_report(ctx: Context) -> str:
    """The report's HTML: the introduction, the summary and every section with data, in page
    order, each opening with its verdict."""
    sections, lines = [], []
    for module in modules():
        body = module.render(ctx)
        if not body:
            continue
        anchor = module.__name__.rsplit(".", 1)[-1]
        verdict = module.verdict(ctx)
        if verdict:
            body = html.verdict(verdict) + "\n" + body
            if hasattr(module, "QUESTION"):
                lines.append((module.QUESTION, verdict, anchor))
        sections.append((anchor, module.TITLE, body))
    intro = _intro(ctx)
    if lines:
        intro += html.summary(lines)
    if not sections:
        intro += html.missing(f"No results under {ctx.results} yet.")
    return html.page(TITLE, sections, intro)


def _remove_unshown_animations(folder: Path, page: str) -> None:
    """Remove the GIFs of ours in ``folder`` that ``page`` does not show (a held-out point or
    a model no longer in the config), so the folder holds the page's animations only."""
    if not folder.is_dir():
        return
    for path in folder.glob("*.gif"):
        if f'src="{html.ANIMATIONS}/{path.name}"' in page:
            continue
        try:
            check_output(path, ANIMATION)
        except OutputExistsError:  # not ours: left alone
            continue
        path.unlink()


def _unseen(ctx: Context) -> list[str]:
    """The scenarios of the transfer points, in their order."""
    return list(dict.fromkeys(p.scenario for p in by_role(ctx.points, "transfer")))


def _intro(ctx: Context) -> str:
    sweep, learn = ctx.cfg["sweep"], ctx.cfg["learn"]
    n = {r: len(by_role(ctx.points, r)) for r in ROLES}
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    numbers = lambda xs: ", ".join(fmt_number(x) for x in xs)  # noqa: E731
    text = html.paragraph(
        f"dozerlab {__version__}, built {when}. Scenarios {', '.join(sweep['scenarios'])}; "
        f"blade speeds {numbers(sweep['speeds'])} m/s × cut depths {numbers(sweep['depths'])} m: "
        f"{n['train']} training points; held out of training, {n['interpolation']} interpolation "
        f"and {n['extrapolation']} extrapolation points"
        + (
            f", and {n['transfer']} on unseen terrain ({', '.join(_unseen(ctx))})"
            if n["transfer"]
            else ""
        )
        + f". Models: {', '.join(learn['models'])}."
    )
    if ctx.cfg.get("report", {}).get("smoke_test"):
        text += html.note(
            f"Smoke test (report.smoke_test). This configuration checks that the pipeline runs "
            f"end to end, with {n['train']} training points and {learn['epochs']} training "
            "epochs: its forces and model errors are not results. The default sweep "
            "(config/config.yaml) is the experiment."
        )
    return text
