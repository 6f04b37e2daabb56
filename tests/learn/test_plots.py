"""Figures of training and validation."""

from matplotlib.figure import Figure

from dozerlab.learn.plots import draw_losses, loss_curves


def test_a_closed_form_fit_gets_bars_not_a_one_point_curve(tmp_path):
    ax = Figure().subplots()
    draw_losses(ax, [0.12], [0.25], "linear: loss")
    assert [round(p.get_width(), 2) for p in ax.patches] == [0.12, 0.25] and not ax.lines
    assert "no epochs" in ax.get_title()
    assert loss_curves([0.12], [0.25], tmp_path / "loss.png").read_bytes()[:4] == b"\x89PNG"


def test_epochs_get_curves_on_a_log_scale():
    ax = Figure().subplots()
    draw_losses(ax, [0.5, 0.3, 0.2], [0.6, 0.4, 0.45])
    assert len(ax.lines) == 2 and ax.get_yscale() == "log" and not ax.patches
    assert ax.get_xlabel() == "epoch"
