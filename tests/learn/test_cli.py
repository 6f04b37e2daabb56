"""``dozerlab train``, ``validate`` and ``evaluate``: their options and their errors."""

import pytest

from dozerlab.cli import build_parser, main
from dozerlab.learn.names import MODEL_NAMES


def test_train_offers_the_model_names_and_validate_defaults_to_no_held_out_points(capsys):
    parser = build_parser()
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args(["train", "--model", "svm", "--train", "a.zarr", "--out", "m"])
    assert exit_.value.code == 2
    assert f"choose from {', '.join(map(repr, MODEL_NAMES))}" in capsys.readouterr().err
    args = parser.parse_args(["validate", "--model", "m", "--out", "v.json"])
    assert (args.interpolation, args.extrapolation, args.plots, args.threads) == ([], [], None, 1)
    args = parser.parse_args(["evaluate", "--model", "m", "a.zarr", "b.zarr"])
    assert args.stores == ["a.zarr", "b.zarr"]


def test_a_missing_model_directory_is_named(tmp_path, capsys):
    assert main(["evaluate", "--model", str(tmp_path / "nowhere"), str(tmp_path / "a.zarr")]) == 2
    err = capsys.readouterr().err
    assert "not a dozerlab model directory" in err and str(tmp_path / "nowhere") in err


def test_a_store_given_twice_is_refused_naming_both(store_files, tmp_path, capsys, monkeypatch):
    """``train --train F F`` counted the point twice; a copy of a store is the same point."""
    import shutil

    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")  # validate logs its refusal otherwise
    one = store_files["train"][0]
    copy = tmp_path / "copy.zarr"
    shutil.copytree(one, copy)
    config = '{"learn": {"epochs": 1}, "mlflow": {"enabled": false}}'
    out = tmp_path / "model"
    for stores, why in (([one, one], "the same file"), ([one, copy], "the same sweep point")):
        argv = ["train", "--model", "linear", "--train", *map(str, stores)]
        assert main([*argv, "--config", config, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"field stores {stores[0]} and {stores[1]} are {why}" in err
        assert "Traceback" not in err and not out.exists()
    held = store_files["interpolation"][0]
    model = tmp_path / "trained"
    argv = ["train", "--model", "linear", "--train", *map(str, store_files["train"])]
    assert main([*argv, "--config", config, "--out", str(model)]) == 0
    assert main(["evaluate", "--model", str(model), str(held), str(held)]) == 2
    assert f"field stores {held} and {held} are the same file" in capsys.readouterr().err
    argv = ["validate", "--model", str(model), "--interpolation", str(held)]
    assert main([*argv, "--extrapolation", str(held), "--out", str(tmp_path / "v.json")]) == 2
    assert "are the same file" in capsys.readouterr().err
    assert not (tmp_path / "v.json").exists()


@pytest.mark.parametrize("threads", ["0", "-2", "1.5", "2000"])
def test_threads_outside_the_configs_bounds_are_refused_before_any_work(
    store_files, tmp_path, capsys, threads
):
    argv = ["train", "--model", "linear", "--train", str(store_files["train"][0])]
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--out", str(tmp_path / "m"), "--threads", threads])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "argument --threads:" in err
    assert "config field 'threads.train'" in err or "is not an integer" in err
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize("device", ["cuda", "cuda:7", "gpu7", "meta"])
def test_a_device_this_machine_lacks_is_one_line_before_any_work(
    store_files, tmp_path, capsys, device
):
    import torch

    if device.startswith("cuda") and torch.cuda.device_count() > 7:
        pytest.skip("this machine has the device")
    out = tmp_path / "m"
    argv = ["train", "--model", "linear", "--train", str(store_files["train"][0])]
    config = '{"mlflow": {"enabled": false}}'
    assert main([*argv, "--config", config, "--out", str(out), "--device", device]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"dozerlab train: error: --device '{device}'") and err.count("\n") == 1
    assert not out.exists()
