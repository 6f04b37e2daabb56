"""The reduced-simulation section: per dynamics model its table with the targets, per point
its plots and animation."""

from dozerlab.config import load_config
from dozerlab.report.sections import reduced
from tests.helpers import SMALL_SWEEP, reduced_json, report_context

CFG = load_config(SMALL_SWEEP)


def test_a_comparison_becomes_a_table_and_a_block_of_plots(tmp_path):
    assert reduced.render(report_context(CFG, tmp_path)) is None
    reduced_json(tmp_path, "replay")
    text = reduced.render(report_context(CFG, tmp_path))
    assert "<h3>replay</h3>" in text and "replay feeds the loop NDEM's own fields" in (
        text.replace("&#x27;", "'")
    )
    assert (
        "targets: height accuracy ≥ 80%, force x rel. RMSE ≤ 25%, loop ≥ 50×, job ≥ 5×, "
        "overlap ≤ 10% of a radius, nothing left the bed" in text
    )
    cells = (
        "<td>90.0</td><td>30.0</td><td>20.0</td><td>10.0</td><td>4.2</td><td>5.0</td>"
        "<td>0</td><td>62.0</td><td>–</td>"
    )
    assert cells in text
    assert (
        "<summary>hill: speed 0.75 m/s, depth 0.1 m — targets missed: force_rmse</summary>" in text
    )
    assert "data:image/png;base64," in text and "data:image/gif" not in text
    assert text.count("<figure>") == 2  # the listed plot that is not there is left out
    # the animation is a file beside the page, shown by its relative path
    name = "reduced_replay_hill_speed~0.75_depth~0.1.gif"
    assert f'<img src="animations/{name}"' in text
    assert (tmp_path / "report" / "animations" / name).read_bytes() == b"GIF89a"
    assert "<p>replay fields and the linear-loop force model: height accuracy 90.0 %" in text


def test_the_verdict_is_the_learned_models_then_the_replay_control(tmp_path):
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["replay", "ridge"]}})
    assert reduced.verdict(report_context(cfg, tmp_path)) is None
    reduced_json(tmp_path, "replay")
    assert reduced.verdict(report_context(cfg, tmp_path)) == (
        "replay fields and the linear-loop force model: height accuracy 90.0 %, draft force rel. "
        "RMSE 30.0 %, loop 62.0× as fast as NDEM's (mean of 1 held-out point); every target met "
        "on 0 of 1 (missed: force_rmse)."
    )
    reduced_json(tmp_path, "ridge")
    verdict = reduced.verdict(report_context(cfg, tmp_path))
    assert verdict.startswith("ridge fields and the linear-loop force model: height accuracy")
    assert verdict.endswith(
        "Control, replay (NDEM's own fields: the loop's own error): height accuracy 90.0 %, draft "
        "force rel. RMSE 30.0 %."
    )
