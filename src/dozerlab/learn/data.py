"""Datasets of (fields, blade velocity) → (force, torque) samples from field stores.

A store is small (a few hundred steps of a ~24×20×12 grid), so it is loaded whole into
contiguous float32 arrays; batches are gathered by index from those in-memory tensors and the
model, not the loader, sets the pace. Samples never cross stores: a sample with a history of
H steps uses steps t-H+1 … t of one store and is labelled with the force/torque of step t.

The split is by sweep point: the stores passed to training are the training points; held-out
points (interpolation, extrapolation) are only ever read by validation. Early stopping needs
its own data, so ``validation_fraction`` of each training store is kept out of the gradient and
out of the normalisation statistics: short blocks spread over the run by default, since a run's
end (the largest pile, the blade near its goal) is not like the rest of it, and a model stopped
on it stops early and extrapolates worse (BENCHMARKS.md). It is the same sweep point as the
training samples, so its loss is optimistic; the held-out points are the real measure.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.runtime import DozerlabError
from dozerlab.sweep import SweepPoint

TARGET_NAMES = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")


@dataclass
class StoreData:
    """One sweep point's samples in memory.

    velocity (T, Nx, Ny, Nz, 3) m/s, density (T, Nx, Ny, Nz) kg/m³, blade_velocity (T, 3) m/s,
    target (T, 6) force N then torque N·m, time (T,) s; all float32 and C-contiguous.
    ``row_dt`` (s) is the time between rows (0 where unknown) and ``bin_size`` (m) the bins' edge
    lengths (None where unknown); the field-evolution models need both for the blade frame's
    shift per row, and models refuse stores of other bin sizes.
    """

    velocity: np.ndarray
    density: np.ndarray
    blade_velocity: np.ndarray
    target: np.ndarray
    time: np.ndarray
    point: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    row_dt: float = 0.0
    #: the store's bin size (x, y, z) in m; None where the source does not say
    bin_size: tuple[float, float, float] | None = None
    #: (x0, y0, y1, z1): bins [x0:, y0:y1, :z1] lie in front of the blade, across it and up to
    #: its top (:attr:`dozerlab.fields.sampling.SamplingGrid.blade_part`); None: the whole grid
    blade_part: tuple[int, int, int, int] | None = None

    @property
    def grid(self) -> tuple[int, int, int]:
        nx, ny, nz = (int(n) for n in self.density.shape[1:4])
        return nx, ny, nz

    @property
    def part(self) -> tuple[int, int, int, int]:
        """:attr:`blade_part`, the whole grid where the store does not say."""
        _, ny, nz = self.grid
        return self.blade_part or (0, 0, ny, nz)

    @property
    def name(self) -> str:
        p = self.point
        if {"scenario", "speed", "depth"} <= p.keys():
            return f"{p['scenario']} v = {p['speed']:g} m/s, d = {p['depth']:g} m"
        return Path(self.source).stem or "store"


def point_key(point: dict[str, Any]) -> tuple[str, str] | None:
    """The sweep point's identity (:attr:`dozerlab.sweep.SweepPoint.key`: scenario and
    canonical name) of a store's labels, or None when a label is missing."""
    if not {"scenario", "speed", "depth"} <= point.keys() or None in point.values():
        return None
    return SweepPoint(str(point["scenario"]), float(point["speed"]), float(point["depth"])).key


def blade_part_of(a: Sequence[int]) -> tuple[int, int, int, int]:
    """A blade part's four bin indices (x0, y0, y1, z1) as ints; DozerlabError otherwise."""
    if len(a) != 4:
        raise DozerlabError(f"a blade part is four bin indices (x0, y0, y1, z1), got {list(a)}")
    return int(a[0]), int(a[1]), int(a[2]), int(a[3])


def _f32(a: Any) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32))


def from_arrays(
    velocity: np.ndarray,
    density: np.ndarray,
    blade_velocity: np.ndarray,
    force: np.ndarray,
    torque: np.ndarray,
    *,
    time: np.ndarray | None = None,
    point: dict[str, Any] | None = None,
    source: str = "",
    row_dt: float = 0.0,
    bin_size: Sequence[float] | None = None,
    blade_part: Sequence[int] | None = None,
) -> StoreData:
    """Build a :class:`StoreData` from arrays shaped like a field store's, checking shapes."""
    v, rho = _f32(velocity), _f32(density)
    if v.ndim != 5 or v.shape[-1] != 3:
        raise DozerlabError(
            f"{source or 'store'}: velocity must be (time, Nx, Ny, Nz, 3), got {v.shape}"
        )
    if rho.shape != v.shape[:4]:
        raise DozerlabError(
            f"{source or 'store'}: density {rho.shape} does not match velocity {v.shape[:4]}"
        )
    steps = v.shape[0]
    target = np.concatenate([_f32(force), _f32(torque)], axis=1)
    vb = _f32(blade_velocity)
    if target.shape != (steps, 6) or vb.shape != (steps, 3):
        raise DozerlabError(
            f"{source or 'store'}: force/torque/blade_velocity must be ({steps}, 3)"
        )
    t = _f32(np.arange(steps) if time is None else time)
    return StoreData(
        v,
        rho,
        vb,
        np.ascontiguousarray(target),
        t,
        dict(point or {}),
        source,
        float(row_dt),
        None if bin_size is None else (float(bin_size[0]), float(bin_size[1]), float(bin_size[2])),
        None if blade_part is None else blade_part_of(blade_part),
    )


def load_store(path: str | Path) -> StoreData:
    """Read a whole field store into memory; a clear error if it lacks a variable."""
    from dozerlab.fields.reader import read_field
    from dozerlab.fields.store import open_store

    ds = open_store(path)  # checks the schema and for damage (lost chunks, NaN, time order)
    point = {k: v for k in ("scenario", "speed", "depth") if (v := ds.attrs.get(k)) is not None}
    return from_arrays(
        read_field(path, "velocity"),
        read_field(path, "density"),
        ds["blade_velocity"].values,
        ds["force"].values,
        ds["torque"].values,
        time=ds["time"].values,
        point=point,
        source=str(path),
        row_dt=float(ds.attrs.get("dt") or 0.0) * float(ds.attrs.get("sample_every") or 1),
        bin_size=ds.attrs.get("bin_size") or None,
        blade_part=ds.attrs.get("blade_part") or None,
    )


def check_grid(
    stores: list[StoreData],
    grid: tuple[int, int, int] | None = None,
    bin_size: Sequence[float] | None = None,
    *,
    distinct: bool = True,
    blade_part: Sequence[int] | None = None,
) -> tuple[int, int, int]:
    """The common grid of ``stores`` (or ``grid`` if given); DozerlabError on any mismatch.

    ``bin_size`` (m; default: the first store's that has one) must match every store's that
    has one: a model learns forces per bin, so the same bin counts over another volume are
    other fields. So must the blade part (:attr:`StoreData.part`; default: the first store's).
    With ``distinct``, the stores are of distinct points (:func:`check_distinct`).
    """
    if not stores:
        raise ValueError("no field stores given (at least one is needed)")
    if distinct:
        check_distinct(stores)
    expected = stores[0].grid if grid is None else (int(grid[0]), int(grid[1]), int(grid[2]))
    sizes = [s.bin_size for s in stores if s.bin_size is not None]
    size = tuple(bin_size) if bin_size is not None else (sizes[0] if sizes else None)
    for s in stores:
        if s.grid != expected:
            raise DozerlabError(
                f"field store {s.source or s.name} has a {s.grid} grid but the model expects {expected}; "
                "models only apply to stores sampled with the same sampling.bins"
            )
        if (
            size is not None
            and s.bin_size is not None
            and not np.allclose(s.bin_size, size, rtol=1e-5)
        ):
            raise DozerlabError(
                f"field store {s.source or s.name} has bins of {list(s.bin_size)} m but the model expects "
                f"{list(size)} m; models only apply to stores sampled with the same sampling volume and bins"
            )
    part = stores[0].part if blade_part is None else blade_part_of(blade_part)
    for s in stores:
        if s.part != part:
            raise DozerlabError(
                f"field store {s.source or s.name} has its blade part at bins {list(s.part)} "
                f"(x0, y0, y1, z1) but the model expects {list(part)}; models only apply to "
                "stores sampled with the same sampling.behind_bins, side_bins and above_bins"
            )
    return expected


def check_distinct(stores: list[StoreData]) -> None:
    """Refuse (DozerlabError naming both) two stores that are one file or one sweep point: a
    point given twice would count twice in training and in every mean over points."""
    seen: dict[Any, StoreData] = {}
    for s in stores:
        keys: list[tuple[str, Any]] = [("file", str(Path(s.source).resolve()))] if s.source else []
        if (point := point_key(s.point)) is not None:
            keys.append(("point", point))
        for key in keys:
            if key in seen:
                first = seen[key]
                why = "the same file" if key[0] == "file" else f"the same sweep point ({s.name})"
                raise DozerlabError(
                    f"field stores {first.source or first.name} and {s.source or s.name} are "
                    f"{why}; give each point once"
                )
            seen.setdefault(key, s)


def with_loop_fields(ndem: StoreData, loop: StoreData) -> StoreData:
    """``ndem``'s samples with the velocity and density of ``loop``, the reduced loop's run of
    the same point: the fields the loop makes, paired row by row with NDEM's force and torque.

    A force model fitted to NDEM's fields reads the loop's fields wrongly (the learned fields
    are not NDEM's: taller, noisier piles); fitted to these it learns the force the loop's
    fields stand for. The two stores must be of one point, grid and bin size, with the same
    row times (a reduced store has one row per NDEM row); DozerlabError otherwise.
    """
    what = f"{loop.source or loop.name} (loop fields) and {ndem.source or ndem.name} (NDEM)"
    if point_key(loop.point) != point_key(ndem.point):
        raise DozerlabError(f"{what} are runs of different points: {loop.point} and {ndem.point}")
    check_grid([ndem, loop], distinct=False)
    if loop.time.shape != ndem.time.shape or not np.allclose(loop.time, ndem.time, atol=1e-6):
        raise DozerlabError(
            f"{what} have different rows ({loop.time.size} and {ndem.time.size}, or other "
            "times): a reduced run of the point gives one row per NDEM row"
        )
    return replace(
        ndem,
        velocity=loop.velocity,
        density=loop.density,
        source=f"{ndem.source} with the fields of {loop.source}",
    )


@dataclass
class Samples:
    """Samples over concatenated stores: ``index[i]`` is the row of sample i's current step.

    Rows ``index[i] - history + 1 … index[i]`` are its history, always within one store.
    ``store_of[i]`` says which store it came from.
    """

    velocity: np.ndarray
    density: np.ndarray
    blade_velocity: np.ndarray
    target: np.ndarray
    index: np.ndarray
    store_of: np.ndarray
    history: int

    def __len__(self) -> int:
        return int(self.index.size)

    def rows(self, sel: np.ndarray) -> np.ndarray:
        """(len(sel), history) rows of the history of the selected samples, oldest first."""
        return self.index[sel, None] + np.arange(1 - self.history, 1)[None, :]

    def subset(self, mask: np.ndarray) -> Samples:
        """The samples where ``mask`` holds (the arrays are shared, not copied)."""
        return Samples(
            self.velocity,
            self.density,
            self.blade_velocity,
            self.target,
            self.index[mask],
            self.store_of[mask],
            self.history,
        )


def concat(stores: list[StoreData], history: int) -> Samples:
    """All samples of ``stores`` with ``history`` steps each (the first history-1 steps of a
    store only serve as history)."""
    if history < 1:
        raise ValueError(f"learn.history must be >= 1, got {history}")
    check_grid(stores)
    index, store_of, start = [], [], 0
    for k, s in enumerate(stores):
        steps = s.target.shape[0]
        if steps < history:
            raise DozerlabError(
                f"{s.source or s.name}: {steps} steps is fewer than learn.history = {history}"
            )
        index.append(np.arange(start + history - 1, start + steps))
        store_of.append(np.full(steps - history + 1, k))
        start += steps
    cat = lambda name: np.ascontiguousarray(np.concatenate([getattr(s, name) for s in stores]))  # noqa: E731
    return Samples(
        cat("velocity"),
        cat("density"),
        cat("blade_velocity"),
        cat("target"),
        np.concatenate(index),
        np.concatenate(store_of),
        history,
    )


def split_train_validation(
    samples: Samples, fraction: float, block: int = 0
) -> tuple[Samples, Samples]:
    """Split each store's samples into training samples and ``fraction`` of them for early stopping.

    ``block > 0``: the validation samples are every k-th block of ``block`` consecutive samples
    (k = round(1 / fraction)), spread over the run so that they see the same phases of it as the
    training samples; the ``history`` samples after each validation block, whose inputs overlap
    it, are used for neither. ``block == 0``, or a store shorter than four blocks: one trailing
    block (the end of the run). At least one sample each.
    """
    if not 0 < fraction < 1:
        raise ValueError(f"learn.validation_fraction must be in (0, 1), got {fraction}")
    if block < 0:
        raise ValueError(f"learn.validation_block must be >= 0, got {block}")
    is_val = np.zeros(len(samples), dtype=bool)
    unused = np.zeros(len(samples), dtype=bool)
    for k in np.unique(samples.store_of):
        where = np.flatnonzero(samples.store_of == k)
        n = where.size
        if n < 2:
            raise DozerlabError(f"store {k} has {n} sample(s); at least 2 are needed to split")
        if block > 0 and 4 * block <= n:
            every = max(2, round(1.0 / fraction))
            val = (np.arange(n) // block) % every == every // 2
            after = np.zeros(n, dtype=bool)
            for end in np.flatnonzero(val[:-1] & ~val[1:]) + 1:
                after[end : end + samples.history] = True
            is_val[where[val]] = True
            unused[where[after & ~val]] = True
        else:
            is_val[where[-min(max(1, round(fraction * n)), n - 1) :]] = True
    return samples.subset(~is_val & ~unused), samples.subset(is_val)
