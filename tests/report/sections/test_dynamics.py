"""The field-evolution section: errors against persistence, the verdict on the targets."""

import html
import json

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.sections import dynamics
from tests.helpers import SMALL_SWEEP, report_context


def _overall(velocity: float, density: float, mass: float) -> dict:
    """Metrics of a group whose velocity error grows linearly along the rollout: ``velocity``
    at one step, 5 × ``velocity`` at 50 steps."""
    return {
        "one_step": {"velocity": velocity, "density": density},
        "rollout_at": {
            k: {"steps": int(k), "velocity": velocity * int(k) / 10, "density": density}
            for k in ("10", "50", "100")
        },
        "rollout": {"velocity": [velocity * k / 10 for k in range(1, 101)]},
        "mass": {"max_abs_error": mass},
    }


def _write(results, model: str, velocity: float, mass: float) -> None:
    point = {"name": "hill speed~0.75_depth~0.1", **_overall(velocity, 0.1, mass)}
    doc = {
        "summary": f"{model}: done",
        "history": 2,
        "horizon": 1,
        "groups": {"interpolation": {"overall": _overall(velocity, 0.1, mass), "points": [point]}},
    }
    path = P.dynamics_validation_path(results, model)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))


CFG = load_config(SMALL_SWEEP)


def test_the_best_model_is_judged_against_persistence(tmp_path):
    assert dynamics.render(report_context(CFG, tmp_path)) is None
    _write(tmp_path, "ridge", 0.1, 0.02)
    alone = dynamics.render(report_context(CFG, tmp_path))
    assert "No persistence baseline validated" in alone
    _write(tmp_path, "persistence", 0.2, 0.0)
    _write(tmp_path, "unet", 0.15, 0.01)
    text = dynamics.render(report_context(CFG, tmp_path))
    assert (
        "Best model per held-out group — interpolation: ridge, velocity error 0.50× persistence's one "
        "step and 0.50× at 50 steps, mass within 2.0 % (meets the targets ≤ 0.6× and ±5 %)."
    ) in html.unescape(text)
    # ratio columns: ridge 0.1 / 0.2 one step and 0.5 / 1.0 at 50 steps
    assert "<td>0.500</td><td>0.500</td></tr>" in text
    assert 'id="dynamics-unet"' in text and "history 2 rows, horizon 1" in text


def test_a_model_off_the_mass_target_misses(tmp_path):
    _write(tmp_path, "persistence", 0.2, 0.0)
    _write(tmp_path, "ridge", 0.1, 0.08)
    text = dynamics.render(report_context(CFG, tmp_path))
    assert "mass within 8.0 % (misses the targets" in text
