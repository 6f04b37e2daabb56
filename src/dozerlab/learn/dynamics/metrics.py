"""Errors of an evolution model on a store: one row ahead, and along autoregressive rollouts
started from true fields.

Velocity error: sqrt(Σ ρ|v − v_true|²) / sqrt(Σ ρ|v_true|²), world frame, with ρ the true
density, so empty bins count for nothing; density error: the relative L2
sqrt(Σ (ρ − ρ_true)²) / sqrt(Σ ρ_true²). The sums run over bins and over the windows (or the
rollouts' starts) they are reported for, so per-point and overall figures are ratios of sums,
not means of ratios. Mass: Σ ρ·V_bin in the sampling volume, predicted over true, along the
rollout.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dozerlab.learn.data import StoreData
from dozerlab.learn.dynamics.models import DynamicsModel

#: Rollout steps reported on their own (or the run's end, where it comes sooner).
REPORTED_STEPS = (10, 50, 100)


def error_sums(
    v: torch.Tensor, rho: torch.Tensor, v_true: torch.Tensor, rho_true: torch.Tensor
) -> np.ndarray:
    """(…, 4) numerator and denominator sums of the velocity and density errors over the
    grid: [Σρ|Δv|², Σρ|v|², Σ(Δρ)², Σρ²] of fields (…, X, Y, Z[, 3]) (float64)."""
    v, rho, v_true, rho_true = (a.double() for a in (v, rho, v_true, rho_true))
    dims = (-3, -2, -1)
    return torch.stack(
        [
            (rho_true * ((v - v_true) ** 2).sum(-1)).sum(dims),
            (rho_true * (v_true**2).sum(-1)).sum(dims),
            ((rho - rho_true) ** 2).sum(dims),
            (rho_true**2).sum(dims),
        ],
        dim=-1,
    ).numpy()


def ratios(sums: np.ndarray) -> dict[str, float]:
    """Velocity and density errors of summed :func:`error_sums` (4,)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return {
            "velocity": float(np.sqrt(sums[0] / sums[1])) if sums[1] > 0 else float("nan"),
            "density": float(np.sqrt(sums[2] / sums[3])) if sums[3] > 0 else float("nan"),
        }


def _tensors(store: StoreData) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (
        torch.from_numpy(store.velocity),
        torch.from_numpy(store.density),
        torch.from_numpy(store.blade_velocity),
    )


@torch.no_grad()
def one_step_sums(model: DynamicsModel, store: StoreData, batch: int = 32) -> np.ndarray:
    """(4,) error sums of the first predicted row over every window of the store."""
    v, rho, vb = _tensors(store)
    h, m = model.history, model.horizon
    last = np.arange(h - 1, rho.shape[0] - m)
    total = np.zeros(4)
    for i in range(0, last.size, batch):
        t = torch.from_numpy(last[i : i + batch])
        past = t[:, None] + torch.arange(1 - h, 1)[None, :]
        ctrl = t[:, None] + torch.arange(1 - h, m + 1)[None, :]
        pv, prho = model(v[past], rho[past], vb[ctrl])
        total += error_sums(pv[:, 0], prho[:, 0], v[t + 1], rho[t + 1]).sum(0)
    return total


@torch.no_grad()
def rollout(
    model: DynamicsModel, store: StoreData, steps: int, starts: int
) -> dict[str, np.ndarray]:
    """Autoregressive rollouts of ``min(steps, rows − history)`` rows from ``starts`` true
    states spread over the run, batched; the blade velocity is the store's (the control is
    known). Returns ``sums`` (L, 4) error sums per rollout step (summed over starts), ``mass``
    and ``mass_true`` (S, L) kg, ``fields`` the predicted and true density (S, L, X, Y, Z) and
    ``starts`` (S,) the last true rows."""
    v, rho, vb = _tensors(store)
    h, m, n = model.history, model.horizon, rho.shape[0]
    length = min(steps, n - h)
    t0 = np.unique(np.linspace(h - 1, n - 1 - length, starts).round().astype(int))
    t0_t = torch.from_numpy(t0)
    past = t0_t[:, None] + torch.arange(1 - h, 1)[None, :]
    cur_v, cur_rho = v[past], rho[past]
    pred_v, pred_rho = [], []
    for k in range(0, length, m):
        ctrl = (t0_t[:, None] + k + torch.arange(1 - h, m + 1)[None, :]).clamp_max(n - 1)
        pv, prho = model(cur_v, cur_rho, vb[ctrl])
        pred_v.append(pv)
        pred_rho.append(prho)
        cur_v = torch.cat([cur_v, pv], 1)[:, -h:]
        cur_rho = torch.cat([cur_rho, prho], 1)[:, -h:]
    pv = torch.cat(pred_v, 1)[:, :length]
    prho = torch.cat(pred_rho, 1)[:, :length]
    rows = t0_t[:, None] + torch.arange(1, length + 1)[None, :]
    true_v, true_rho = v[rows], rho[rows]
    volume = float(np.prod(model.bin_size))
    return {
        "sums": error_sums(pv, prho, true_v, true_rho).sum(0),
        "mass": prho.double().sum((-3, -2, -1)).numpy() * volume,
        "mass_true": true_rho.double().sum((-3, -2, -1)).numpy() * volume,
        "fields": np.stack([prho.numpy(), true_rho.numpy()]),
        "starts": t0,
    }


def summarize(
    one: np.ndarray, sums: np.ndarray, mass: np.ndarray, mass_true: np.ndarray
) -> dict[str, Any]:
    """Metrics of summed one-step sums (4,), rollout sums (L, 4) and masses (S, L)."""
    curve = [ratios(s) for s in sums]
    with np.errstate(divide="ignore", invalid="ignore"):
        mass_ratio = mass.sum(0) / mass_true.sum(0)
        per_start = np.abs(mass / mass_true - 1.0)
    at = {}
    for k in REPORTED_STEPS:
        j = min(k, len(curve)) - 1
        at[str(k)] = {"steps": j + 1, **curve[j]}
    window = min(100, mass.shape[1])
    return {
        "one_step": ratios(one),
        "rollout_at": at,
        "rollout": {
            "velocity": [c["velocity"] for c in curve],
            "density": [c["density"] for c in curve],
            "mass_ratio": [float(x) for x in mass_ratio],
        },
        "mass": {
            "steps": window,
            "max_abs_error": float(np.nanmax(np.abs(mass_ratio[:window] - 1.0))),
            "worst_rollout_error": float(np.nanmax(per_start[:, :window])),
        },
    }


def evaluate_store(
    model: DynamicsModel, store: StoreData, steps: int, starts: int
) -> dict[str, Any]:
    """Metrics of one store, with the raw sums (``_sums``, ``_rollout``) for aggregation."""
    one = one_step_sums(model, store)
    roll = rollout(model, store, steps, starts)
    return {
        "name": store.name,
        "point": store.point,
        "store": store.source,
        "rows": int(store.density.shape[0]),
        "starts": [int(t) for t in roll["starts"]],
        **summarize(one, roll["sums"], roll["mass"], roll["mass_true"]),
        "_sums": one,
        "_rollout": roll,
    }


def combine(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Overall metrics of evaluated points: sums added, each rollout step over the points that
    reach it."""
    one = sum(p["_sums"] for p in points)
    length = max(p["_rollout"]["sums"].shape[0] for p in points)
    sums = np.zeros((length, 4))
    mass = np.zeros((1, length))
    mass_true = np.zeros((1, length))
    for p in points:
        r = p["_rollout"]
        n = r["sums"].shape[0]
        sums[:n] += r["sums"]
        mass[0, :n] += r["mass"].sum(0)
        mass_true[0, :n] += r["mass_true"].sum(0)
    out = summarize(one, sums, mass, mass_true)
    out["mass"]["worst_rollout_error"] = max(p["mass"]["worst_rollout_error"] for p in points)
    return out


def public(point: dict[str, Any]) -> dict[str, Any]:
    """A point's metrics without the raw sums (for JSON)."""
    return {k: v for k, v in point.items() if not k.startswith("_")}
