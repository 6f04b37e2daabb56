"""Figures of training and validation."""

from matplotlib.figure import Figure

from dozerlab.learn.plots import draw_losses, loss_curves


def test_a_closed_form_fit_gets_bars_not_a_one_point_curve(tmp_path):
    ax = Figure().subplots()
    draw_losses(ax, [0.12], [0.25], "linear: loss")
    assert [round(p.get_width(), 2) for p in ax.patches] == [0.12, 0.25] and not ax.lines
    assert "no epochs" in ax.get_title()
    assert loss_curves([0.12], [0.25], tmp_path / "loss.png").read_bytes()[:4] == b"\x89PNG"


def test_epochs_get_curves_on_a_log_scale_numbered_from_one():
    ax = Figure().subplots()
    draw_losses(ax, [0.5, 0.3, 0.2], [0.6, 0.4, 0.45])
    training, validation, kept = ax.lines
    assert ax.get_yscale() == "log" and not ax.patches and ax.get_xlabel() == "epoch"
    # epochs numbered from 1, as the report counts them; the kept one (lowest validation loss)
    assert list(training.get_xdata()) == list(validation.get_xdata()) == [1, 2, 3]
    assert list(kept.get_xdata()) == [2] and kept.get_label() == "kept: epoch 2"
