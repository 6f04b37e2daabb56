"""Windows of field stores for the evolution models: the fields of the last H rows and the blade
velocity of those rows and of the next m (the blade's control is known in advance) → the fields
of the next m rows.

Windows are :class:`~dozerlab.learn.data.Samples` of the force models' data layer, cut where
the next m rows would leave the store, so they never cross stores, and they are split for early
stopping into the same blocks as the force models' samples. The velocity at row t+1 is the one
that moved the particles from t to t+1, and ``blade_velocity`` at row k is the velocity of the
step that made row k: the step from t to t+j moves the grid by blade_velocity[t+j]·Δt.
"""

from __future__ import annotations

import numpy as np
import torch

from dozerlab.learn.data import Samples, StoreData, check_grid, concat
from dozerlab.learn.fitting import SampleTensors
from dozerlab.runtime import DozerlabError


def windows(stores: list[StoreData], history: int, horizon: int) -> Samples:
    """All windows of ``stores`` with ``history`` rows of input and ``horizon`` rows ahead:
    ``index[i]`` is the last input row; rows index+1 … index+horizon are its targets."""
    if horizon < 1:
        raise ValueError(f"dynamics.horizon must be >= 1, got {horizon}")
    for s in stores:
        if s.density.shape[0] < history + horizon:
            raise DozerlabError(
                f"{s.source or s.name}: {s.density.shape[0]} rows is fewer than history + horizon = "
                f"{history + horizon} (dynamics.history; the rows a call predicts, dynamics.horizon or "
                "ridge_horizon, times the calls a training or validation rollout makes)"
            )
    samples = concat(stores, history)
    ends = np.cumsum([s.density.shape[0] for s in stores])
    return samples.subset(samples.index + horizon < ends[samples.store_of])


def frame_of(
    stores: list[StoreData], expected: tuple[float, tuple[float, float, float]] | None = None
) -> tuple[float, tuple[float, float, float]]:
    """The common row interval (s) and bin size (m) of ``stores`` (or ``expected``); a
    DozerlabError names a store whose frame is unknown or differs."""
    check_grid(stores)
    for s in stores:
        if not (s.row_dt > 0 and s.bin_size is not None and all(b > 0 for b in s.bin_size)):
            raise DozerlabError(
                f"{s.source or s.name}: the store lacks its row interval or bin size "
                "(attributes dt, sample_every, bin_size), which the evolution models need"
            )
    first = stores[0].bin_size
    assert first is not None  # checked above
    dt, size = expected or (stores[0].row_dt, first)
    for s in stores:
        assert s.bin_size is not None
        if not np.allclose((s.row_dt, *s.bin_size), (dt, *size), rtol=1e-5):
            raise DozerlabError(
                f"{s.source or s.name}: row interval {s.row_dt} s and bins {s.bin_size} m differ from "
                f"the model's {dt} s and {size} m; evolution models apply to one sampling only"
            )
    return float(dt), (float(size[0]), float(size[1]), float(size[2]))


class WindowBatches(SampleTensors):
    """The windows' store arrays as tensors on ``device``; :meth:`get` gathers a batch."""

    def get(self, sel: np.ndarray, horizon: int) -> tuple[torch.Tensor, ...]:
        """velocity (B, H, X, Y, Z, 3), density (B, H, X, Y, Z), blade_velocity (B, H + m, 3) of
        the inputs, and the true velocity (B, m, …, 3) and density (B, m, …) of the next m rows."""
        h = self.samples.history
        rows = torch.from_numpy(
            self.samples.index[sel, None] + np.arange(1 - h, horizon + 1)[None, :]
        ).to(self.device)
        past, ahead = rows[:, :h], rows[:, h:]
        return (
            self.velocity[past],
            self.density[past],
            self.blade_velocity[rows],
            self.velocity[ahead],
            self.density[ahead],
        )
