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
