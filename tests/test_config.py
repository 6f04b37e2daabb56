import json
import re

import pytest

from dozerlab.cli import main
from dozerlab.config import (
    ConfigError,
    ConfigWarning,
    check_memory,
    load_config,
    memory_estimate,
)


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
        ({"sweep": {"scenarios": ["dune"]}}, "sweep.scenarios[0]", "one of"),
        (
            {"sweep": {"interpolation": [{"scenario": "hill", "speed": -1, "depth": 0.1}]}},
            "sweep.interpolation[0].speed",
            ">= 0.01",
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


def test_a_job_given_the_blade_but_not_the_bed_hears_nothing_of_the_default_beds_gap(recwarn):
    # the default bed (10 cm grains, 1.2 m) beside the default sweep's 0.7 m blade would wedge
    load_config({"blade": {"width": 0.7}})
    assert not [w for w in recwarn if issubclass(w.category, ConfigWarning)]


@pytest.mark.parametrize(
    ("doc", "field", "allowed"),
    [
        ({"sweep": {"speeds": [1.0, 1.0, 1]}}, "sweep.speeds", "each value once"),
        ({"sweep": {"depths": [0.05, 0.05]}}, "sweep.depths", "each value once"),
        ({"sweep": {"speeds": ["1e9"]}}, "sweep.speeds[0]", "<= 20"),
    ],
)
def test_duplicates_and_big_numbers_name_field_and_range(doc, field, allowed):
    with pytest.raises(
        ConfigError, match=rf"config field '{re.escape(field)}'.*allowed: {allowed}"
    ):
        load_config(doc)


def test_numbers_in_exponent_form_are_numbers(tmp_path):
    """YAML 1.1 (PyYAML, Snakemake) reads 1e0 as a string; a user means a number."""
    path = tmp_path / "c.yaml"
    path.write_text("solver: {dt: 1E-2}\nsweep: {speeds: [1e0, 15e-1]}\n")
    cfg = load_config(path)
    assert cfg["sweep"]["speeds"] == [1.0, 1.5] and cfg["solver"]["dt"] == 0.01
    assert (
        load_config({"seed": 3, "mlflow": {"experiment": "1e3"}})["mlflow"]["experiment"] == "1e3"
    )


@pytest.mark.parametrize(
    ("dynamics", "field", "allowed"),
    [
        ({"ridge_z_bands": [4, 1]}, "dynamics.ridge_z_bands", "within 1..7"),
        ({"ridge_z_bands": [8]}, "dynamics.ridge_z_bands", "within 1..7"),
        ({"ridge_y_bands": [3, 18]}, "dynamics.ridge_y_bands", "within 1..17"),
    ],
)
def test_ridge_bands_outside_the_sampling_volume_are_refused(dynamics, field, allowed):
    sampling = {"bins": [16, 12, 8], "side_bins": 3}
    with pytest.raises(ConfigError, match=rf"'{re.escape(field)}'.*{re.escape(allowed)}"):
        load_config({"dynamics": dynamics, "sampling": sampling})
    load_config(
        {"dynamics": {"ridge_y_bands": [3, 15], "ridge_z_bands": [1, 7]}, "sampling": sampling}
    )


def test_held_out_point_on_the_training_grid_is_refused_by_config():
    held = [{"scenario": "hill", "speed": 1, "depth": 0.1}]  # 1 and 1.0 are one point
    with pytest.raises(ConfigError, match=r"'sweep.extrapolation\[0\]'.*already in the sweep grid"):
        load_config({"sweep": {"speeds": [1.0], "depths": [0.1], "extrapolation": held}})


@pytest.mark.parametrize(
    ("sweep", "field"),
    [
        ({"depths": [0.05, 0.2]}, "sweep.depths[1]"),
        (
            {"depths": [0.05], "interpolation": [{"scenario": "step", "speed": 1.2, "depth": 0.4}]},
            "sweep.interpolation[0].depth",
        ),
    ],
)
def test_cuts_deeper_than_the_bed_are_refused(sweep, field):
    doc = {
        "bed": {"radius": 0.025},
        "scenarios": {
            "hill": {"base_height": 0.1, "goal_height": 0.24},
            "step": {"low_height": 0.35, "goal_height": 0.3},
        },
        "sweep": sweep,
    }
    hill = field == "sweep.depths[1]"
    level, low = ("0.24", "base_height 0.1") if hill else ("0.35", "low_height 0.35")
    with pytest.raises(ConfigError) as exc:
        load_config(doc)
    assert f"config field '{field}'" in str(exc.value)
    assert f"at least {level} m high" in str(exc.value) and low in str(exc.value)
    assert "allowed: depth <= " in str(exc.value)
    doc["sweep"] = {"depths": [0.05, 0.19]}
    load_config(doc)  # a grain diameter (0.05 m) above the ground at the lowest cut: accepted


def test_jobs_larger_than_the_machine_are_refused_with_the_figure():
    with pytest.raises(ConfigError, match=r"sampling.bins .* about 1.15e\+03 GiB.*bins \[1024"):
        load_config({"sampling": {"bins": [1024, 1024, 1024]}})
    cfg = load_config("config/quick.yaml")
    check_memory(cfg, available=2**40)
    with pytest.raises(ConfigError, match=r"a train job would need about .* GiB"):
        check_memory(cfg, available=2**20)
    assert memory_estimate(cfg)["train"] > memory_estimate(cfg)["simulate"]


def test_config_command_names_bad_yaml_and_leaks_without_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sweep: {speeds: [1.0, 2.0}\n")
    assert main(["config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"configuration file {bad} is not valid YAML" in err and "Traceback" not in err
    leak = tmp_path / "leak.yaml"
    leak.write_text(
        "sweep: {speeds: [1.0], depths: [0.1], interpolation: [{scenario: hill, speed: 1, depth: 0.1}]}\n"
    )
    assert main(["config", str(leak)]) == 2
    assert "already in the sweep grid" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        ({"solver": {"dt": float("nan")}}, "solver.dt"),
        (
            {"reduced": {"projection": {"relaxation": float("nan")}}},
            "reduced.projection.relaxation",
        ),
        ({"learn": {"ridge_alpha": float("inf")}}, "learn.ridge_alpha"),
        ({"bed": {"settle_kinetic_energy": float("inf")}}, "bed.settle_kinetic_energy"),
        ({"solver": {"gravity": [0.0, 0.0, float("-inf")]}}, "solver.gravity[2]"),
        ({"sweep": {"speeds": [1.0, float("nan")]}}, "sweep.speeds[1]"),
    ],
)
def test_non_finite_numbers_are_refused_by_field(doc, field):
    """NaN compares false with every bound, so it passed the ranges; infinity passed the open
    ones (ridge_alpha: inf trained a constant predictor)."""
    with pytest.raises(ConfigError) as exc:
        load_config(doc)
    assert f"config field '{field}'" in str(exc.value)
    assert "is not a finite number (allowed: a finite number)" in str(exc.value)
    assert str(exc.value).count("config field") == 1  # not its bounds as well


@pytest.mark.parametrize(
    ("doc", "field", "allowed"),
    [
        ({"learn": {"epochs": 3.0}}, "learn.epochs", "a whole number, written without a point"),
        ({"sampling": {"bins": [8, 8.0, 4]}}, "sampling.bins[1]", "a whole number"),
        ({"learn": {"batch_size": True}}, "learn.batch_size", "a whole number"),
        ({"seed": 99999999999999999999999}, "seed", "<= 4294967295"),
        ({"seed": 2**32}, "seed", "<= 4294967295"),
        ({"sweep": {"speeds": [1e-9]}}, "sweep.speeds[0]", ">= 0.01"),
        ({"sweep": {"depths": [1.0e-250]}}, "sweep.depths[0]", ">= 0.001"),
        (
            {"sweep": {"extrapolation": [{"scenario": "hill", "speed": 0.001, "depth": 0.1}]}},
            "sweep.extrapolation[0].speed",
            ">= 0.01",
        ),
    ],
)
def test_integers_seed_speeds_and_depths_are_bounded(doc, field, allowed):
    with pytest.raises(ConfigError) as exc:
        load_config(doc)
    assert f"config field '{field}'" in str(exc.value) and allowed in str(exc.value)


def test_the_bounds_and_the_whole_numbers_that_remain_valid():
    cfg = load_config(
        {
            "seed": 2**32 - 1,
            "learn": {"epochs": 3},
            "sweep": {"speeds": [0.01, 0.5], "depths": [0.05]},
            "bed": {"length": 1.0},
        }
    )
    assert cfg["seed"] == 2**32 - 1 and cfg["learn"]["epochs"] == 3


def test_a_key_given_twice_is_refused_naming_file_and_lines(tmp_path, capsys):
    path = tmp_path / "twice.yaml"
    path.write_text("learn:\n  epochs: 5\nsolver: {dt: 0.01}\nlearn:\n  epochs: 7\n")
    assert main(["config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"dozerlab config: error: configuration file {path} gives the key 'learn' twice in one "
        "mapping (lines 1 and 4; allowed: each key once)"
    )
    path.write_text("solver: {dt: 0.01, dt: 0.02}\n")
    with pytest.raises(ConfigError, match="the key 'dt' twice"):
        load_config(path)
    with pytest.raises(ConfigError, match="inline configuration gives the key 'seed' twice"):
        load_config('{"seed": 1, "seed": 2}')


def test_a_binary_config_file_is_one_line_naming_it(tmp_path, capsys):
    path = tmp_path / "config.yaml"
    path.write_bytes(b"seed: 1\n\x89PNG\r\n\x1a\n\x00\xff\xfe")
    assert main(["config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert f"configuration file {path} is not UTF-8 text (byte 8 is 0x89)" in err


def test_the_config_command_names_the_file_and_every_bad_field(tmp_path, capsys):
    path = tmp_path / "c.yaml"
    path.write_text("solver: {dt: .nan}\nlearn: {ridge_alpha: .inf, epochs: 3.0}\n")
    assert main(["config", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"error: configuration file {path}: invalid configuration" in err
    for line in (
        "'learn.epochs': 3.0 is not of type 'integer'",
        "'learn.ridge_alpha': inf is not a finite number",
        "'solver.dt': nan is not a finite number",
    ):
        assert line in err


def test_check_value_gives_a_flag_the_fields_bounds():
    from dozerlab.config import check_value

    check_value(("sweep", "speeds", 0), 0.5)
    with pytest.raises(
        ConfigError, match=r"--speed: 0\.001 is less than the minimum of 0\.01 .*'sweep\.speeds'"
    ):
        check_value(("sweep", "speeds", 0), 0.001, "--speed")
    with pytest.raises(ConfigError, match="not a finite number"):
        check_value(("sweep", "depths", 0), float("nan"))
