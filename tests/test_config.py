import json

import pytest

from dozerlab.config import ConfigError, load_config


def test_defaults_fill_a_partial_document():
    cfg = load_config({"solver": {"dt": 0.02}})
    assert cfg["solver"]["dt"] == 0.02
    assert cfg["solver"]["iterations"] == 50
    assert cfg["scenarios"]["hill"]["goal_height"] > 0
    assert cfg["sweep"]["scenarios"] == ["hill", "step"]


def test_inline_json_and_file(tmp_path):
    assert load_config(json.dumps({"seed": 3}))["seed"] == 3
    path = tmp_path / "c.yaml"
    path.write_text("sampling:\n  bins: [8, 8, 4]\n")
    assert load_config(path)["sampling"]["bins"] == [8, 8, 4]


@pytest.mark.parametrize(
    "doc, field, allowed",
    [
        ({"solver": {"dt": 0}}, "solver.dt", "> 0"),
        ({"solver": {"iterations": 0}}, "solver.iterations", ">= 1"),
        ({"material": {"poisson_ratio": 0.7}}, "material.poisson_ratio", "<= 0.5"),
        ({"sweep": {"scenarios": ["dune"]}}, "sweep.scenarios.0", "one of"),
        ({"sweep": {"interpolation": [{"scenario": "hill", "speed": -1, "depth": 0.1}]}},
         "sweep.interpolation.0.speed", "> 0"),
        ({"blade": {"colour": "red"}}, "blade", "only the fields"),
    ],
)
def test_bad_values_name_field_and_range(doc, field, allowed):
    with pytest.raises(ConfigError) as exc:
        load_config(doc)
    assert f"'{field}'" in str(exc.value)
    assert allowed in str(exc.value)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
