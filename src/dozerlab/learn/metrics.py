"""Error metrics of force/torque predictions, per component."""

from __future__ import annotations

import numpy as np

from dozerlab.learn.data import TARGET_NAMES


def component_metrics(pred: np.ndarray, true: np.ndarray) -> dict[str, dict[str, float]]:
    """Per component of (N, 6) predictions and measurements: ``rmse`` (N or N·m),
    ``rel_rmse`` (RMSE / RMS of the measured value; NaN where that RMS is 0) and ``r2``
    (1 − SSE/SST; NaN where the measurement is constant)."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    if pred.shape != true.shape or pred.ndim != 2 or pred.shape[1] != len(TARGET_NAMES):
        raise ValueError(f"pred and true must both be (N, 6), got {pred.shape} and {true.shape}")
    err = pred - true
    rmse = np.sqrt(np.mean(err**2, axis=0))
    rms = np.sqrt(np.mean(true**2, axis=0))
    sst = np.sum((true - true.mean(axis=0)) ** 2, axis=0)
    sse = np.sum(err**2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(rms > 0, rmse / rms, np.nan)
        r2 = np.where(sst > 0, 1.0 - sse / sst, np.nan)
    return {
        name: {"rmse": float(rmse[i]), "rel_rmse": float(rel[i]), "r2": float(r2[i])}
        for i, name in enumerate(TARGET_NAMES)
    }


def flat(metrics: dict[str, dict[str, float]], prefix: str) -> dict[str, float]:
    """``{prefix}.{component}.{metric}`` keys for MLflow, finite values only."""
    return {
        f"{prefix}.{comp}.{name}": value
        for comp, values in metrics.items()
        for name, value in values.items()
        if np.isfinite(value)
    }
