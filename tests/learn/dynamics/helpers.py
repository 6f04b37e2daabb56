"""Synthetic stores whose field evolution follows a known rule."""

from __future__ import annotations

import numpy as np

from dozerlab.learn.data import StoreData, from_arrays

GRID = (10, 5, 4)
BIN = (0.1, 0.1, 0.1)
DT = 0.01
#: Bins per row the material moves against the blade (the rule of :func:`translating`).
SHIFT = 1


def translating(
    seed: int, *, rows: int = 40, decay: float = 0.97, grid=GRID, speed: float = 1.25
) -> StoreData:
    """Material that moves one bin per row against the blade's motion, its density falling by
    ``decay`` each row: the blade moves ``speed`` bins per row, the material ``speed − 1`` in
    the same direction, so ρ_{t+1}(x) = decay · ρ_t(x + 1) exactly. A quarter of the bins are
    empty (zero velocity); the material's velocity is uniform."""
    rng = np.random.default_rng(seed)
    length = grid[0] + rows * SHIFT + 2
    bed = rng.uniform(800, 1600, (length, *grid[1:])) * (rng.random((length, *grid[1:])) > 0.25)
    rows_ = np.arange(rows)
    density = np.stack([bed[t * SHIFT : t * SHIFT + grid[0]] * decay**t for t in rows_])
    vb = np.zeros((rows, 3), np.float32)
    vb[:, 0] = speed * BIN[0] / DT
    velocity = np.zeros((*density.shape, 3), np.float32)
    velocity[..., 0] = np.where(density > 0, (speed - SHIFT) * BIN[0] / DT, 0.0)
    zeros = np.zeros((rows, 3), np.float32)
    return from_arrays(
        velocity,
        density.astype(np.float32),
        vb,
        zeros,
        zeros,
        time=rows_ * DT,
        point={"scenario": "hill", "speed": 1.0 + seed / 10, "depth": 0.1},
        row_dt=DT,
        bin_size=BIN,
    )


def steady(rows: int = 20, grid=GRID) -> StoreData:
    """A field that does not change: material carried along with the blade."""
    rng = np.random.default_rng(5)
    density = np.repeat(rng.uniform(500, 1500, (1, *grid)), rows, axis=0).astype(np.float32)
    vb = np.zeros((rows, 3), np.float32)
    vb[:, 0] = 1.0
    velocity = np.zeros((*density.shape, 3), np.float32)
    velocity[..., 0] = 1.0
    zeros = np.zeros((rows, 3), np.float32)
    return from_arrays(
        velocity,
        density,
        vb,
        zeros,
        zeros,
        point={"scenario": "hill", "speed": 1.0, "depth": 0.2},
        row_dt=DT,
        bin_size=BIN,
    )
