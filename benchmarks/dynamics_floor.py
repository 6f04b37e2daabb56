"""What the held-out stores let any field-evolution model reach one row ahead.

    python benchmarks/dynamics_floor.py --results results [--config config/config.yaml]

For each held-out point of the config's sweep, from its store alone (no model is trained):

- one row ahead, the mass-weighted world-frame velocity error (the validate-dynamics metric) of
  ``persistence`` (row t for row t+1), of the last row carried one row ahead by the models'
  own advection (:func:`dozerlab.learn.dynamics.advection.advect`), and of an oracle that knows
  the future: the mean of rows t and t+2. Grain-scale noise that changes from row to row is
  what no causal model of the binned fields can predict; the oracle averages it over two rows
  and still keeps part of it, so its ratio to persistence bounds from below what a model's
  one-row figure can be, give or take what a model might learn of the noise's pattern.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.learn.data import load_store
from dozerlab.learn.dynamics.advection import advect


def velocity_error(pred: np.ndarray, true: np.ndarray, rho: np.ndarray) -> float:
    """sqrt(Σ ρ|v − v_true|²) / sqrt(Σ ρ|v_true|²) over every row and bin given."""
    w = rho.astype(np.float64)
    num = (w * np.square(pred - true, dtype=np.float64).sum(-1)).sum()
    return float(np.sqrt(num / (w * np.square(true, dtype=np.float64).sum(-1)).sum()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results")
    ap.add_argument("--config", default="config/config.yaml")
    args = ap.parse_args()
    cfg = load_config(args.config)
    for point in P.sweep_points(cfg):
        if point.role == "train":
            continue
        s = load_store(P.field_path(args.results, point))
        v, rho, vb = s.velocity, s.density, s.blade_velocity
        assert s.bin_size is not None
        t = np.arange(1, rho.shape[0] - 1)  # predicting row t from row t - 1
        _, v_adv = advect(
            torch.from_numpy(rho[t - 1]),
            torch.from_numpy(v[t - 1]),
            torch.from_numpy(vb[t]),
            s.row_dt,
            s.bin_size,
        )
        pers = velocity_error(v[t - 1], v[t], rho[t])
        adv = velocity_error(v_adv.numpy(), v[t], rho[t])
        oracle = velocity_error(0.5 * (v[t - 1] + v[t + 1]), v[t], rho[t])
        print(
            f"{point.role:13s} {point.scenario} {point.name}: one row ahead, persistence "
            f"{pers:.3f}, advected {adv:.3f} ({adv / pers:.2f}x), mean of the rows before and "
            f"after (future known) {oracle:.3f} ({oracle / pers:.2f}x)"
        )


if __name__ == "__main__":
    main()
