import json

import pytest

from dozerlab.config import ConfigError, ConfigWarning, load_config


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
    ("doc", "field", "allowed"),
    [
        ({"solver": {"dt": 0}}, "solver.dt", "> 0"),
        ({"solver": {"iterations": 0}}, "solver.iterations", ">= 1"),
        ({"material": {"poisson_ratio": 0.7}}, "material.poisson_ratio", "<= 0.5"),
        ({"sweep": {"scenarios": ["dune"]}}, "sweep.scenarios.0", "one of"),
        (
            {"sweep": {"interpolation": [{"scenario": "hill", "speed": -1, "depth": 0.1}]}},
            "sweep.interpolation.0.speed",
            "> 0",
        ),
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


def _leaves(doc, prefix=""):
    """Dotted paths of the scalar and list fields of a nested mapping."""
    for key, value in doc.items():
        if isinstance(value, dict):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}"


def test_quick_config_sets_every_field_the_default_sets():
    # Snakemake lays quick.yaml over config.yaml key by key: a field only the default sets
    # would leak into the quick sweep (a 1.2 m end margin on its 2 m bed, say).
    from pathlib import Path

    import yaml

    root = Path(__file__).resolve().parents[1] / "config"
    default = yaml.safe_load((root / "config.yaml").read_text())
    quick = yaml.safe_load((root / "quick.yaml").read_text())
    assert set(_leaves(default)) <= set(_leaves(quick))
    load_config(root / "quick.yaml")


@pytest.mark.parametrize("name", ["config.yaml", "quick.yaml"])
def test_shipped_configs_leave_no_wedging_gap(name, recwarn):
    from pathlib import Path

    load_config(Path(__file__).resolve().parents[1] / "config" / name)
    load_config({})
    assert not [w for w in recwarn if issubclass(w.category, ConfigWarning)]


def test_a_gap_where_grains_wedge_is_flagged():
    # 5 cm grains, 5 cm between each blade end and wall: one grain jams there
    with pytest.warns(ConfigWarning, match=r"'bed.width' and 'blade.width'.*1 grain diameters"):
        load_config({"bed": {"width": 0.8, "radius": 0.025}, "blade": {"width": 0.7}})
