"""Figures of the evolution models: error and mass along the rollout, predicted next to true
density slices."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.learn.plots import _figure, _save
from dozerlab.runtime import FIGURE, atomic_output, png_metadata


def rollout_curves(series: dict[str, dict[str, Any]], path: str | Path, title: str = "") -> Path:
    """Velocity and density error (relative, log scale) and predicted/true mass against the
    rollout step, one line per entry of ``series`` (each a metrics dict's ``rollout``)."""
    fig, axes = _figure(3, width=4.2)
    for label, r in series.items():
        steps = np.arange(1, len(r["velocity"]) + 1)
        axes[0, 0].plot(steps, r["velocity"], label=label)
        axes[0, 1].plot(steps, r["density"], label=label)
        axes[0, 2].plot(steps, r["mass_ratio"], label=label)
    axes[0, 0].set(xlabel="rollout step", ylabel="velocity error (mass-weighted)", yscale="log")
    axes[0, 1].set(xlabel="rollout step", ylabel="density relative L2", yscale="log")
    axes[0, 2].axhspan(0.95, 1.05, color="0.9")
    axes[0, 2].set(xlabel="rollout step", ylabel="mass in volume, predicted / true")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(title)
    return _save(fig, Path(path))


def density_slices(fields: np.ndarray, steps: list[int], path: str | Path, title: str = "") -> Path:
    """Density (kg/m³) on the blade's centre plane (x forward, z up) of one rollout, predicted
    (top) next to true (bottom) at the given rollout steps; ``fields`` (2, L, X, Y, Z)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3.0 * len(steps), 4.6), layout="constrained")
    grid = fig.subplots(2, len(steps), squeeze=False)
    y = fields.shape[3] // 2
    hi = float(fields[:, :, :, y].max()) or 1.0
    for j, k in enumerate(steps):
        for i, label in enumerate(("predicted", "true")):
            ax = grid[i, j]
            im = ax.imshow(
                fields[i, k - 1, :, y].T, origin="lower", vmin=0, vmax=hi, cmap="viridis"
            )
            ax.set(title=f"{label}, step {k}", xlabel="x bin", ylabel="z bin")
    fig.colorbar(im, ax=grid, shrink=0.7, label="density (kg/m³)")
    fig.suptitle(title)
    with atomic_output(path, FIGURE) as tmp:
        fig.savefig(tmp, dpi=110, format="png", metadata=png_metadata())
    return Path(path)
