"""``dozerlab report``: the command writes the page of the results it finds."""

import json

from dozerlab.cli import build_parser, main
from dozerlab.report.html import REPORT_PAGE
from tests.helpers import SMALL_SWEEP


def test_defaults_are_the_workflow_paths():
    args = build_parser().parse_args(["report"])
    assert (args.config, args.results, args.out) == (None, "results", "results/report/index.html")


def test_report_command_writes_the_page_and_refuses_a_foreign_file(tmp_path, capsys):
    out = tmp_path / "index.html"
    argv = ["report", "--config", json.dumps(SMALL_SWEEP), "--results", str(tmp_path / "r")]
    assert main([*argv, "--out", str(out)]) == 0
    text = out.read_text()
    assert REPORT_PAGE.recognise(out) and f"No results under {tmp_path / 'r'} yet." in text
    assert "Scenarios hill; blade speeds 0.5, 1.0 m/s × cut depths 0.1 m: 2 training points" in text
    mine = tmp_path / "mine.html"
    mine.write_text("my notes")
    assert main([*argv, "--out", str(mine)]) == 2
    assert str(mine) in capsys.readouterr().err and mine.read_text() == "my notes"
