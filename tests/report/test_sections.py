"""The section registry: every module of ``dozerlab.report.sections`` is a complete section."""

from dozerlab.report import sections


def test_every_section_module_is_complete():
    found = sections.modules()
    assert [m.ORDER for m in found] == sorted(m.ORDER for m in found)
    for m in found:
        assert isinstance(m.TITLE, str) and callable(m.render)


def test_a_figure_a_result_json_names_outside_the_results_is_skipped_with_a_warning(
    tmp_path, capsys
):
    """A validation or comparison JSON is data: a figure it names is read only when it is a file
    under the results folder; one outside it, missing or not a name is skipped, said on stderr."""
    import json

    from dozerlab import sweep as P
    from dozerlab.config import load_config
    from dozerlab.report.sections import models, reduced
    from tests.helpers import SMALL_SWEEP, png_file, reduced_json, report_context, validation_json

    results = tmp_path / "results"
    (results / "validation").mkdir(parents=True)
    secret = png_file(tmp_path / "secret.png", "outside")  # a real PNG, beside the results
    validation_json(results, "linear")
    path = P.validation_path(results, "linear")
    doc = json.loads(path.read_text())
    doc["plots"] = {
        "parity": "linear/parity.png",
        "loss": "../../secret.png",
        "series": {"absolute": str(secret), "missing": "linear/none.png", "odd": 3},
    }
    path.write_text(json.dumps(doc))
    cfg = load_config({**SMALL_SWEEP, "learn": {"models": ["linear"]}})
    text = models.render(report_context(cfg, results))
    assert text.count("data:image/png;base64,") == 2  # the comparison's chart and the parity plot
    assert "linear: predicted vs measured force" in text and "force over time" not in text
    assert "training and validation loss" not in text
    err = capsys.readouterr().err
    for name, why in (
        ("'../../secret.png'", "is outside the results folder"),
        (repr(str(secret)), "is outside the results folder"),
        ("'linear/none.png'", "is not a file"),
        ("3", "is not a file name"),
    ):
        assert f"dozerlab report: {path} names {name}, which {why}: skipped" in err, err

    # a comparison's animation outside the results is neither copied beside the page nor shown
    reduced_json(results, "ridge")
    cmp_path = P.reduced_comparison_path(results, "ridge")
    cmp_doc = json.loads(cmp_path.read_text())
    (tmp_path / "secret.gif").write_bytes(b"GIF89a")
    cmp_doc["points"][0]["plots"] = ["../../../../secret.gif"]
    cmp_path.write_text(json.dumps(cmp_doc))
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["ridge"]}})
    ctx = report_context(cfg, results)
    text = reduced.render(ctx)
    assert "secret" not in text and not (ctx.page_dir / "animations").exists()
    assert "which is outside the results folder: skipped" in capsys.readouterr().err
