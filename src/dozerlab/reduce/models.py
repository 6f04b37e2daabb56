"""The learned parts the reduced loop drives: a field-evolution model and a force model.

Field-evolution models come as MLflow pyfunc directories (``results/dynamics/{model}/``, the
contract of the "Field-evolution models" issue): ``predict`` takes ``{"velocity": (B,H,Nx,Ny,Nz,3),
"density": (B,H,Nx,Ny,Nz), "blade_velocity": (B,H+m,3)}`` float32 arrays as a store holds them and
returns ``{"velocity": (B,m,Nx,Ny,Nz,3), "density": (B,m,Nx,Ny,Nz)}`` in physical units, with H
and m in the model's metadata as ``history`` and ``horizon``. :class:`ReplayFieldModel` answers
the same questions with a stored NDEM run's fields (the truth): with it, the loop's own error —
advection and projection — shows alone.

Force models are the pyfuncs of ``results/models/{model}/`` (``dozerlab.learn.pyfunc``); they
read the last ``learn.history`` rows of fields.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from dozerlab.learn.dynamics.inference import RidgeInference
from dozerlab.learn.dynamics.pyfunc import FORMAT as DYNAMICS_FORMAT
from dozerlab.learn.dynamics.pyfunc import predict_arrays
from dozerlab.learn.inference import LinearForceRows
from dozerlab.learn.pyfunc import FORMAT as FORCE_FORMAT
from dozerlab.learn.pyfunc import check_inputs, with_history
from dozerlab.learn.pyfunc import predict_arrays as predict_force_rows
from dozerlab.runtime import DozerlabError

#: The dynamics-model name that replays the point's own NDEM store.
REPLAY = "replay"
#: Rows a force model other than a linear one reads at once after the loop. With batches of 256
#: and torch's first call in the loop's time, that pass took 0.45-0.72 ms a row of the default
#: sweep's reduce jobs; in batches of 16 after a first call at load, 0.10-0.17 ms, the same
#: numbers (BENCHMARKS.md, "The loop's force rows in small batches").
FORCE_BATCH = 16


class FieldModel(Protocol):
    """What the loop asks of a field-evolution model."""

    name: str
    history: int
    horizon: int

    def predict(
        self, velocity: np.ndarray, density: np.ndarray, blade_velocity: np.ndarray, row: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Fields of rows row+1 … row+m from rows row-H+1 … row (one run, no batch axis).

        velocity (H, Nx, Ny, Nz, 3) m/s, density (H, Nx, Ny, Nz) kg/m³, blade_velocity (H+m, 3)
        m/s → velocity (m, Nx, Ny, Nz, 3), density (m, Nx, Ny, Nz).
        """
        ...

    def check_run(self, run: RunFrame) -> None:
        """Refuse (:class:`DozerlabError`, naming both sides) a run whose rows, bins, bin size
        or labels this model's fields do not fit."""
        ...


@dataclass(frozen=True)
class RunFrame:
    """What a reduced run is, for the checks of its models: its source (``trajectory``, a path
    for messages), sampled ``rows``, bin counts ``bins``, bin edge lengths ``bin_size`` (m), the
    time between rows ``row_dt`` (s), its labels ``point`` (scenario, speed m/s, depth m;
    a label may be None where not given) and the grid's ``blade_part``
    (:attr:`dozerlab.fields.sampling.SamplingGrid.blade_part`; None: the whole grid)."""

    trajectory: str
    rows: int
    bins: tuple[int, int, int]
    bin_size: tuple[float, float, float]
    row_dt: float
    point: dict[str, Any]
    blade_part: tuple[int, int, int, int] | None = None


def _check_frame(what: str, bins: tuple[int, ...], bin_size: Any, run: RunFrame) -> None:
    """Refuse bins or bin sizes of ``what`` (a model or store, for messages) other than the run's
    (the config's sampling section)."""
    if tuple(bins) != tuple(run.bins):
        raise DozerlabError(
            f"{what} has {tuple(bins)} bins but the run samples {tuple(run.bins)} "
            "(the config's sampling.bins); both must be the same"
        )
    if bin_size is not None and not np.allclose(bin_size, run.bin_size, rtol=1e-5):
        raise DozerlabError(
            f"{what} has bins of {[float(b) for b in bin_size]} m but the run's are "
            f"{list(run.bin_size)} m (the config's sampling section); both must be the same"
        )


class PyfuncFieldModel:
    """A field-evolution model of an MLflow pyfunc directory, read directly (``FORMAT.load``):
    the loop calls the network itself, without MLflow's per-call input handling (it cost as
    much as the network on the quick sweep's grid; BENCHMARKS.md, "Measurements behind the
    defaults") or the 1–2 s of importing MLflow."""

    def __init__(self, path: str | Path, grid: tuple[int, int, int]) -> None:
        path = Path(path)
        if not (path / "MLmodel").is_file():
            raise DozerlabError(f"not an MLflow model directory (no MLmodel): {path}")
        self.module, _meta = DYNAMICS_FORMAT.load(path)
        self.name = path.name
        self.history = int(self.module.history)
        self.horizon = int(self.module.horizon)
        self.grid = grid
        # the ridge's forward compiled: 1.63-1.64 ms a call against the module's 8.7-8.9 ms on
        # the default grid (BENCHMARKS.md, "The ridge's sums, three layers a pass")
        self.ridge = RidgeInference(self.module) if self.module.kind == "ridge" else None

    def predict(
        self, velocity: np.ndarray, density: np.ndarray, blade_velocity: np.ndarray, row: int
    ) -> tuple[np.ndarray, np.ndarray]:
        h, m = self.history, self.horizon
        shapes = (velocity.shape, density.shape, blade_velocity.shape)
        if self.ridge is not None and shapes == ((h, *self.grid, 3), (h, *self.grid), (h + m, 3)):
            return self.ridge.predict(velocity, density, blade_velocity)
        out = predict_arrays(
            self.module,
            {
                "velocity": velocity[None],
                "density": density[None],
                "blade_velocity": blade_velocity[None],
            },
        )
        v, rho = out["velocity"], out["density"]
        if v.shape != (1, m, *self.grid, 3) or rho.shape != (1, m, *self.grid):
            raise DozerlabError(
                f"dynamics model {self.name} returned velocity {v.shape} and density {rho.shape}; "
                f"expected (1, {m}, {', '.join(map(str, self.grid))}[, 3]) (sampling.bins)"
            )
        return v[0], rho[0]

    def check_run(self, run: RunFrame) -> None:
        _check_frame(
            f"dynamics model {self.name}",
            self.module.grid,
            getattr(self.module, "bin_size", None),
            run,
        )
        self.grid = run.bins


class ReplayFieldModel:
    """The fields of a stored run, as if predicted: rows row+1 … row+m of the store.

    Rows past the store's end repeat its last row.
    """

    def __init__(self, store: str | Path, *, history: int = 1, horizon: int = 1) -> None:
        from dozerlab.learn.data import load_store

        data = load_store(store)
        self.data = data
        self.name = REPLAY
        self.history = int(history)
        self.horizon = int(horizon)
        self.velocity = data.velocity
        self.density = data.density
        self.grid = data.grid

    def predict(
        self, velocity: np.ndarray, density: np.ndarray, blade_velocity: np.ndarray, row: int
    ) -> tuple[np.ndarray, np.ndarray]:
        last = self.density.shape[0] - 1
        rows = np.minimum(np.arange(row + 1, row + 1 + self.horizon), last)
        return self.velocity[rows], self.density[rows]

    def check_run(self, run: RunFrame) -> None:
        """The replayed store must be the run's point: its labels, one row per sampled step of
        the trajectory, the same bins and bin size and row interval."""
        from dozerlab.learn.data import point_key

        d = self.data
        what = f"NDEM store {d.source}"
        given = {k: v for k, v in run.point.items() if v is not None}
        stored = {k: d.point[k] for k in given if k in d.point}
        if given.keys() == {"scenario", "speed", "depth"} <= d.point.keys():
            differ = point_key(given) != point_key(d.point)
        else:
            differ = any(
                stored[k] != given[k] if k == "scenario" else not np.isclose(stored[k], given[k])
                for k in stored
            )
        if differ:
            raise DozerlabError(
                f"{what} is the run of {d.point} but the reduced run is of {given} "
                f"(trajectory {run.trajectory}, --scenario/--speed/--depth); replay the point's own store"
            )
        _check_frame(what, d.grid, d.bin_size, run)
        if d.density.shape[0] != run.rows:
            raise DozerlabError(
                f"{what} has {d.density.shape[0]} rows but trajectory {run.trajectory} gives "
                f"{run.rows} sampled rows (its steps // sampling.every); replay the point's own store"
            )
        if d.row_dt > 0 and not np.isclose(d.row_dt, run.row_dt, rtol=1e-6):
            raise DozerlabError(
                f"{what} has {d.row_dt} s between rows but the run {run.row_dt} s "
                "(solver.dt × sampling.every); both must be the same"
            )


class ForcePredictor:
    """A trained force model (``results/models/{model}/``), read directly from its MLflow
    pyfunc directory (``FORMAT.load``, as :class:`PyfuncFieldModel`).

    Attributes: ``history`` (rows of fields it reads), ``name`` (the model's kind, ``-loop``
    added for one trained on a reduced loop's fields).
    """

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        self.module, meta = FORCE_FORMAT.load(path)
        self.history = int(self.module.history)
        # a model trained on a reduced loop's fields (rule train_loop_force) reads "<kind>-loop"
        kind = str(meta.get("kind") or path.name)
        self.name = f"{kind}-loop" if meta.get("loop_fields") else kind
        self.bin_size = meta.get("bin_size")
        # a linear model's rows from the fields' column sums: a tenth of its time through torch
        self._linear = LinearForceRows(self.module) if self.module.kind == "linear" else None
        # torch's first call in a process costs several times the next, and the compiled
        # sums' first call on the loop's float32 fields loads them: made here, it falls in
        # loading the model, not in the loop (FORCE_BATCH)
        grid = tuple(self.module.grid)
        self.predict_rows(
            np.zeros((FORCE_BATCH, *grid, 3), np.float32),
            np.zeros((FORCE_BATCH, *grid), np.float32),
            np.zeros((FORCE_BATCH, 3)),
        )

    def check_run(self, run: RunFrame) -> None:
        """Refuse a run whose bins, bin size or blade part are not those the model was
        trained on."""
        _check_frame(f"force model {self.name}", self.module.grid, self.bin_size, run)
        _, ny, nz = run.bins
        part = run.blade_part or (0, 0, ny, nz)
        if tuple(self.module.blade_part) != tuple(part):
            raise DozerlabError(
                f"force model {self.name} reads bins {list(self.module.blade_part)} (x0, y0, y1, "
                f"z1) as the blade's but the run's blade part is {list(part)} (the config's "
                "sampling.behind_bins, side_bins and above_bins); both must be the same"
            )

    def predict(
        self, velocity: np.ndarray, density: np.ndarray, blade_velocity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Force (3,) N and torque (3,) N·m of the last of the given consecutive rows (T, …)."""
        k = min(self.history, density.shape[0])
        arrays = check_inputs(
            {
                "velocity": velocity[-k:],
                "density": density[-k:],
                "blade_velocity": blade_velocity[-k:],
            },
            self.module.grid,
        )
        # only the last row's window: the pyfunc would run the network on all k of them
        v, rho, vb = (t[-1:] for t in with_history(arrays, self.module.history))
        with torch.no_grad():
            row = self.module(v, rho, vb)[0].double().numpy()
        return row[:3], row[3:6]

    def predict_rows(
        self, velocity: np.ndarray, density: np.ndarray, blade_velocity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Force (T, 3) N and torque (T, 3) N·m of every row of (T, …) consecutive rows, each
        from its own window of rows (as :meth:`predict` of the rows up to it): a linear model's
        by :class:`~dozerlab.learn.inference.LinearForceRows`, any other's in batches."""
        if self._linear is not None:
            out = self._linear(velocity, density, blade_velocity)
            return out[:, :3], out[:, 3:6]
        rows = predict_force_rows(
            self.module,
            {"velocity": velocity, "density": density, "blade_velocity": blade_velocity},
            batch=FORCE_BATCH,
        ).astype(np.float64)
        return rows[:, :3], rows[:, 3:6]


def load_field_model(
    name_or_path: str | Path, grid: tuple[int, int, int], ndem_store: str | Path | None = None
) -> Any:
    """``replay`` (needs ``ndem_store``) or an MLflow pyfunc directory of a dynamics model."""
    if str(name_or_path) == REPLAY:
        if ndem_store is None:
            raise DozerlabError("the replay field model needs the point's NDEM store (--ndem)")
        return ReplayFieldModel(ndem_store)
    return PyfuncFieldModel(name_or_path, grid)
