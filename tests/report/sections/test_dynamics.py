"""The field-evolution section: errors against persistence, the verdict on the targets."""

import html

from dozerlab.config import load_config
from dozerlab.report.sections import dynamics
from tests.helpers import SMALL_SWEEP, dynamics_json, report_context

CFG = load_config(SMALL_SWEEP)


def test_the_best_model_is_judged_against_persistence(tmp_path):
    assert dynamics.render(report_context(CFG, tmp_path)) is None
    dynamics_json(tmp_path, "ridge", 0.1, 0.02)
    alone = dynamics.render(report_context(CFG, tmp_path))
    assert "No persistence baseline validated" in alone
    assert dynamics.verdict(report_context(CFG, tmp_path)) is None
    dynamics_json(tmp_path, "persistence", 0.2, 0.0)
    dynamics_json(tmp_path, "unet", 0.15, 0.01)
    text = dynamics.render(report_context(CFG, tmp_path))
    assert (
        "Best model per held-out group — interpolation: ridge, velocity error 0.50× persistence's one "
        "step and 0.50× at 50 steps, mass within 2.0 % (meets the targets ≤ 0.6× and ±5 %)."
    ) in html.unescape(text)
    # ratio columns: ridge 0.1 / 0.2 one step and 0.5 / 1.0 at 50 steps
    assert "<td>0.500</td><td>0.500</td></tr>" in text
    assert 'id="dynamics-unet"' in text and "history 2 rows, horizon 1" in text
    assert dynamics.verdict(report_context(CFG, tmp_path)) == (
        "ridge evolves the fields best, started from NDEM's: its velocity error is 0.50× "
        "persistence's after one step and 0.50× after 50 steps, mass within 2.0 % (the worse "
        "held-out group); it meets the targets ≤ 0.6× and ±5 %."
    )


def test_a_model_off_the_mass_target_misses(tmp_path):
    dynamics_json(tmp_path, "persistence", 0.2, 0.0)
    dynamics_json(tmp_path, "ridge", 0.1, 0.08)
    text = dynamics.render(report_context(CFG, tmp_path))
    assert "mass within 8.0 % (misses the targets" in text
    assert "; it misses the targets" in dynamics.verdict(report_context(CFG, tmp_path))
