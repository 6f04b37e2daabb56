"""Figures of training and validation: loss curves, force over time, parity."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.runtime import FIGURE, atomic_output, png_metadata


def _figure(ncols: int = 1, width: float = 5.0, height: float = 3.6) -> tuple[Any, Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt, *plt.subplots(1, ncols, figsize=(width * ncols, height), squeeze=False)


def _save(plt: Any, fig: Any, path: Path) -> Path:
    fig.tight_layout()
    with atomic_output(path, FIGURE) as tmp:
        fig.savefig(tmp, dpi=110, format="png", metadata=png_metadata())
    plt.close(fig)
    return path


def loss_curves(
    train_loss: list[float], val_loss: list[float], path: str | Path, title: str = ""
) -> Path:
    """Training and validation loss (normalised MSE) per epoch, log scale."""
    plt, fig, ax = _figure()
    ax = ax[0, 0]
    epochs = np.arange(len(train_loss))
    ax.plot(epochs, train_loss, "o-" if len(epochs) < 3 else "-", label="training")
    ax.plot(epochs, val_loss, "o-" if len(epochs) < 3 else "-", label="validation (early stopping)")
    ax.set(xlabel="epoch", ylabel="MSE of normalised targets", yscale="log", title=title)
    ax.legend()
    return _save(plt, fig, Path(path))


def force_series(
    time: np.ndarray, pred: np.ndarray, true: np.ndarray, path: str | Path, title: str = ""
) -> Path:
    """Predicted vs measured force components (N) over time (s) for one sweep point."""
    plt, fig, axes = _figure(3, width=4.2)
    for i, comp in enumerate("xyz"):
        ax = axes[0, i]
        ax.plot(time, true[:, i], color="k", lw=1, label="measured")
        ax.plot(time, pred[:, i], color="tab:red", lw=1, label="predicted")
        ax.set(xlabel="time (s)", ylabel=f"force {comp} (N)")
    axes[0, 0].legend()
    fig.suptitle(title)
    return _save(plt, fig, Path(path))


def parity(
    groups: dict[str, tuple[np.ndarray, np.ndarray]], path: str | Path, title: str = ""
) -> Path:
    """Predicted vs measured force x and z (N) for each group of held-out points."""
    plt, fig, axes = _figure(2, width=4.2, height=4.2)
    for ax, i, comp in ((axes[0, 0], 0, "x"), (axes[0, 1], 2, "z")):
        lo, hi = np.inf, -np.inf
        for name, (pred, true) in groups.items():
            if len(true):
                ax.scatter(true[:, i], pred[:, i], s=4, alpha=0.5, label=name)
                lo, hi = (
                    min(lo, true[:, i].min(), pred[:, i].min()),
                    max(hi, true[:, i].max(), pred[:, i].max()),
                )
        if np.isfinite(lo):
            ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set(
            xlabel=f"measured force {comp} (N)",
            ylabel=f"predicted force {comp} (N)",
            aspect="equal",
        )
    axes[0, 0].legend()
    fig.suptitle(title)
    return _save(plt, fig, Path(path))
