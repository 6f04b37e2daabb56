"""The command-line arguments the layers share: parsed as the commands parse them, and a
handler's start (the validated config, the thread count from --threads or the config)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from dozerlab.cliargs import add_config, add_labels, add_point, add_threads, labels


def _parser(*adders) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(exit_on_error=False)
    for add in adders:
        add(p)
    return p


def test_labels_default_to_none_and_reach_the_job_as_keywords():
    p = _parser(add_labels)
    assert labels(p.parse_args([])) == {"scenario": None, "speed": None, "depth": None}
    args = p.parse_args(["--scenario", "hill", "--speed", "1.5", "--depth", "0.05"])
    assert labels(args) == {"scenario": "hill", "speed": 1.5, "depth": 0.05}


def test_a_required_point_refuses_a_missing_or_non_numeric_number():
    p = _parser(lambda p: add_point(p, "speed in m/s", "depth in m", required=True))
    assert vars(p.parse_args(["--speed", "2", "--depth", "0.1"])) == {"speed": 2.0, "depth": 0.1}
    with pytest.raises(argparse.ArgumentError, match="speed"):
        p.parse_args(["--speed", "fast", "--depth", "0.1"])
    with pytest.raises(SystemExit):
        p.parse_args(["--speed", "2"])


def _configure(argv: list[str], threads_key: str | None) -> int:
    """numba's thread count after ``configure`` in a fresh process (set_threads is global)."""
    code = (
        "import argparse\n"
        "from dozerlab.cliargs import add_config, add_threads, configure\n"
        "p = argparse.ArgumentParser()\n"
        "add_config(p)\n"
        "add_threads(p, default=None)\n"
        f"configure(p.parse_args({argv!r}), {threads_key!r})\n"
        "import numba\n"
        "print(numba.get_num_threads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return int(out.stdout)


def test_configure_takes_threads_from_the_flag_else_from_the_config():
    config = json.dumps({"threads": {"train": 2}})
    assert _configure(["--config", config, "--threads", "1"], "train") == 1
    assert _configure(["--config", config], "train") == 2


def test_config_and_threads_options_parse_with_their_defaults():
    p = _parser(add_config, add_threads)
    assert vars(p.parse_args([])) == {"config": None, "threads": 1}
    assert p.parse_args(["--threads", "3"]).threads == 3
