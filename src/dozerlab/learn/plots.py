"""Figures of training and validation: loss curves, force over time, parity."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.runtime import FIGURE, atomic_output, png_metadata


def _figure(ncols: int = 1, width: float = 5.0, height: float = 3.6) -> tuple[Any, Any]:
    """A figure and its (1, ncols) axes; matplotlib's object API, as importing pyplot costs
    a job ≈ 0.3 s."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols, height))
    return fig, fig.subplots(1, ncols, squeeze=False)


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    with atomic_output(path, FIGURE) as tmp:
        fig.savefig(tmp, dpi=110, format="png", metadata=png_metadata())
    return path


def loss_curves(
    train_loss: list[float], val_loss: list[float], path: str | Path, title: str = ""
) -> Path:
    """Write :func:`draw_losses` as a PNG at ``path``."""
    fig, ax = _figure()
    draw_losses(ax[0, 0], train_loss, val_loss, title)
    return _save(fig, Path(path))


def draw_losses(ax: Any, train_loss: list[float], val_loss: list[float], title: str = "") -> None:
    """Training and validation loss (MSE of normalised targets) per epoch, log scale, on ``ax``.

    A model fitted in one closed-form solve (the ``linear`` ridge: one loss each, no epochs)
    gets a bar chart of its two losses instead of a curve of one point.
    """
    if len(train_loss) == 1 and len(val_loss) == 1:
        losses = [train_loss[0], val_loss[0]]
        bars = ax.barh(["training", "validation blocks"], losses, color=["C0", "C1"])
        ax.bar_label(bars, labels=[f"{v:.3g}" for v in losses], padding=3)
        ax.set_xlim(0, 1.25 * max(max(losses), 1e-12))
        ax.invert_yaxis()
        ax.set(
            xlabel="MSE of normalised targets",
            title=f"{title}\nclosed-form fit: one solve, no epochs" if title else "closed-form fit",
        )
        return
    # epochs numbered from 1, as the report and the console count them; the kept model is the
    # one of the lowest validation loss (early stopping restores it)
    epochs = np.arange(1, len(train_loss) + 1)
    ax.plot(epochs, train_loss, "o-" if len(epochs) < 3 else "-", label="training")
    ax.plot(epochs, val_loss, "o-" if len(epochs) < 3 else "-", label="validation (early stopping)")
    best = int(np.argmin(val_loss))
    ax.plot(epochs[best], val_loss[best], "k*", ms=11, label=f"kept: epoch {epochs[best]}")
    ax.set(xlabel="epoch", ylabel="MSE of normalised targets", yscale="log", title=title)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.legend()


def force_series(
    time: np.ndarray, pred: np.ndarray, true: np.ndarray, path: str | Path, title: str = ""
) -> Path:
    """Predicted vs measured force components over time (s) for one sweep point, given in N
    and drawn in kN."""
    fig, axes = _figure(3, width=4.2)
    for i, comp in enumerate("xyz"):
        ax = axes[0, i]
        ax.plot(time, true[:, i] / 1000.0, color="k", lw=1, label="measured")
        ax.plot(time, pred[:, i] / 1000.0, color="tab:red", lw=1, label="predicted")
        ax.set(xlabel="time (s)", ylabel=f"force {comp} (kN)")
    axes[0, 0].legend()
    fig.suptitle(title)
    return _save(fig, Path(path))


def parity(
    groups: dict[str, tuple[np.ndarray, np.ndarray]], path: str | Path, title: str = ""
) -> Path:
    """Predicted vs measured force x and z for each group of held-out points, given in N and
    drawn in kN."""
    fig, axes = _figure(2, width=4.2, height=4.2)
    for ax, i, comp in ((axes[0, 0], 0, "x"), (axes[0, 1], 2, "z")):
        lo, hi = np.inf, -np.inf
        for name, (pred, true) in groups.items():
            if len(true):
                t, p = true[:, i] / 1000.0, pred[:, i] / 1000.0
                ax.scatter(t, p, s=4, alpha=0.5, label=name)
                lo, hi = min(lo, t.min(), p.min()), max(hi, t.max(), p.max())
        if np.isfinite(lo):
            ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set(
            xlabel=f"measured force {comp} (kN)",
            ylabel=f"predicted force {comp} (kN)",
            aspect="equal",
        )
    axes[0, 0].legend()
    fig.suptitle(title)
    return _save(fig, Path(path))
