"""``dozerlab train-dynamics`` and ``validate-dynamics``: their options and their errors."""

import pytest

from dozerlab.cli import build_parser, main
from dozerlab.config import schema
from dozerlab.learn.dynamics.cli import MODELS
from dozerlab.learn.dynamics.models import DYNAMICS_MODELS


def test_the_commands_offer_the_schemas_models():
    enum = schema()["properties"]["dynamics"]["properties"]["models"]["items"]["enum"]
    assert list(MODELS) == list(DYNAMICS_MODELS) == enum
    args = build_parser().parse_args(["validate-dynamics", "--model", "m", "--out", "d.json"])
    assert (args.interpolation, args.extrapolation, args.plots, args.threads) == ([], [], None, 1)


def test_an_unknown_model_and_missing_inputs_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(
            ["train-dynamics", "--model", "fno", "--train", "a", "--out", "b"]
        )
    assert "invalid choice: 'fno'" in capsys.readouterr().err
    argv = ["train-dynamics", "--model", "ridge", "--train", str(tmp_path / "a.zarr")]
    assert (
        main([*argv, "--out", str(tmp_path / "m"), "--config", '{"mlflow": {"enabled": false}}'])
        == 2
    )
    assert f"field store not found: {tmp_path / 'a.zarr'}" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
    assert (
        main(["validate-dynamics", "--model", str(tmp_path), "--out", str(tmp_path / "d.json")])
        == 2
    )
    assert "not a dozerlab evolution model directory" in capsys.readouterr().err
